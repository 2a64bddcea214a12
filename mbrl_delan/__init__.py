"""mbrl_delan: model-based RL on TorchRL with Deep Lagrangian Networks as the world model.

Importing `mbrl_delan.envs` registers a gymnasium id for each registered env
(`mbrl_delan.envs.gym_id`, e.g. ``gym.make("mbrl_delan/Pendulum-v0")``); the envs load only
when made.
"""

__version__ = "0.1.0"
