"""The registries (`mbrl_delan.registry`, the package's bottom floor: envs register there
without reaching up into the config code), also importable from here, as plugins written
against ``mbrl_delan.conf.registry`` do."""

from mbrl_delan.registry import (
    ENVS,
    INVERSE_MODELS,
    MODELS,
    PLANNER_METHODS,
    PLANNERS,
    PLUGIN_GROUP,
    Entry,
    EnvSpec,
    PluginError,
    Registry,
    TaskFactory,
    UnknownNameError,
    lacking,
    load_entry_points,
    load_plugins,
    register_env,
    register_inverse_model,
    register_model,
    register_planner,
)

__all__ = [
    "ENVS",
    "INVERSE_MODELS",
    "MODELS",
    "PLANNERS",
    "PLANNER_METHODS",
    "PLUGIN_GROUP",
    "Entry",
    "EnvSpec",
    "PluginError",
    "Registry",
    "TaskFactory",
    "UnknownNameError",
    "lacking",
    "load_entry_points",
    "load_plugins",
    "register_env",
    "register_inverse_model",
    "register_model",
    "register_planner",
]
