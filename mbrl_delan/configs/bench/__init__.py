"""The Hydra config dir of python -m mbrl_delan.bench (pkg://mbrl_delan.configs.bench)."""
