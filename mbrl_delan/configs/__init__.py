"""The entry points' Hydra configs: train/, fit/, bench/ (each a config dir) and launchers/
(hydra/launcher options on every entry point's search path)."""
