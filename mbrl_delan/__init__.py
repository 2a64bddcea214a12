"""mbrl_delan: model-based RL on TorchRL with Deep Lagrangian Networks as the world model."""

__version__ = "0.1.0"
