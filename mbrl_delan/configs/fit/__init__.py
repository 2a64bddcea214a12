"""The Hydra config dir of python -m mbrl_delan.fit (pkg://mbrl_delan.configs.fit)."""
