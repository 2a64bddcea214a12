"""The Hydra config dir of python -m mbrl_delan.train (pkg://mbrl_delan.configs.train)."""
