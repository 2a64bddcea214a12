"""Registries of the parts a run is built from: envs, world models and planners.

Each family maps a name (the config's ``env.name``, ``model.name``, ``planner.name``) to an
entry, filled by a decorator where the part is defined::

    from mbrl_delan.registry import register_model

    @register_model("linear", schema=LinearConfig)
    def build_linear(cfg, system):  # cfg: the model group, system: the env's System
        return LinearModel(system.nq, system.nv, system.nu, cfg.hidden)

The package's own parts register the same way, beside their classes, when their modules are
imported (importing `mbrl_delan.conf` imports them all); a user's module is imported by
naming it in the config's ``plugins`` list (`load_plugins`) or by a Python entry point in the
group ``mbrl_delan.plugins`` (loaded on a registry's first look-up).
See docs/architecture.md, "How to add an env / a task / a model / a planner".
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")
PLUGIN_GROUP = "mbrl_delan.plugins"  # Python entry points loaded with the registries


class UnknownNameError(KeyError):
    """A name no entry of the family is registered under; the message lists the valid ones."""

    def __str__(self) -> str:
        return str(self.args[0])


class PluginError(ImportError):
    """A plugin module could not be imported; the message names it and why."""


@dataclass(frozen=True)
class Entry(Generic[T]):
    """One registered part: `build` makes it from its config group, `schema` types that group
    (a dataclass, or None for an untyped group)."""

    name: str
    build: T
    schema: type | None = None


class Registry(Generic[T]):
    """Name -> `Entry` of one family (``env``, ``model``, ``planner``)."""

    def __init__(self, family: str) -> None:
        self.family = family
        self._entries: dict[str, Entry[T]] = {}
        self._loaded = False

    def add(self, name: str, build: T, schema: type | None = None) -> T:
        """Register `build` as `name`; registering the same object again is a no-op, another
        object under a taken name is a ValueError."""
        old = self._entries.get(name)
        if old is not None and old.build != build:
            raise ValueError(f"{self.family} {name!r} is already registered ({old.build!r})")
        self._entries[name] = Entry(name, build, schema)
        return build

    def register(self, name: str, schema: type | None = None) -> Callable[[T], T]:
        """Decorator form of `add`."""
        return lambda build: self.add(name, build, schema)

    def _load(self) -> None:
        if not self._loaded:
            self._loaded = True
            load_entry_points()

    def __getitem__(self, name: str) -> Entry[T]:
        self._load()
        if name not in self._entries:
            raise UnknownNameError(
                f"{self.family}.name={name!r} is not registered; choose one of: "
                f"{', '.join(self.names())} (a plugin's own names need its module in plugins=[...])"
            )
        return self._entries[name]

    def __contains__(self, name: object) -> bool:
        self._load()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def names(self) -> tuple[str, ...]:
        """The registered names in registration order (the package's own are registered
        once `mbrl_delan.conf` is imported, the entry points' plugins at the first look-up)."""
        self._load()
        return tuple(self._entries)


def load_plugins(modules: Sequence[str]) -> None:
    """Import the user's modules that register parts (the config's ``plugins``); a module that
    cannot be imported is a `PluginError` naming it and the cause."""
    for module in modules:
        try:
            importlib.import_module(module)
        except ImportError as err:
            raise PluginError(f"plugins: cannot import {module!r} ({err})") from err


def load_entry_points() -> None:
    """Import the modules of the installed entry points in the group ``mbrl_delan.plugins``
    (a module already imported is not imported again)."""
    for point in importlib.metadata.entry_points(group=PLUGIN_GROUP):
        log.debug("plugin %s: %s", point.name, point.value)
        point.load()


TaskFactory = Callable[[Any, "int | None", "dict[str, Any]"], Any]


@dataclass(frozen=True)
class EnvSpec:
    """An env: the MuJoCo system and how to make its task.

    asset: the MJCF, as a stem under ``mbrl_delan/systems/assets``, a path, or a function
        returning the path (for files found at run time).
    frame_skip: MuJoCo steps per control step.
    make_task: (system, episode_len or None for the task's default, task options) -> Task.
    options: the task options the env takes (config ``env.task``) with their defaults.
    physics: the MJCF the env simulates where it differs from `asset`, the one the world
        models are given (an env whose physics the models' structure cannot express); None:
        the asset.
    """

    asset: str | Path | Callable[[], Path]
    frame_skip: int
    make_task: TaskFactory
    options: Mapping[str, Any] | None = None
    physics: str | Path | Callable[[], Path] | None = None


def register_env(
    name: str,
    asset: str | Path | Callable[[], Path],
    frame_skip: int,
    options: Mapping[str, Any] | None = None,
    physics: str | Path | Callable[[], Path] | None = None,
) -> Callable[[TaskFactory], TaskFactory]:
    """Decorator: register the decorated task factory, with its MJCF `asset` and `frame_skip`,
    as env `name` (see `EnvSpec`)."""

    def add(make_task: TaskFactory) -> TaskFactory:
        ENVS.add(name, EnvSpec(asset, frame_skip, make_task, options, physics))
        return make_task

    return add


# the package's own parts register themselves beside their classes, in the modules
# `mbrl_delan.conf` imports; the registry names none of them
ENVS: Registry[Any] = Registry("env")
MODELS: Registry[Any] = Registry("model")
PLANNERS: Registry[Any] = Registry("planner")
# fit's inverse-dynamics models (python -m mbrl_delan.fit model=NAME)
INVERSE_MODELS: Registry[Any] = Registry("model")
# fit's data kinds (python -m mbrl_delan.fit data=NAME): each a `DataKind`
FIT_DATA: Registry[Any] = Registry("data")
register_model = MODELS.register  # builder: (model config group, System) -> WorldModel
# what the planning policy calls on a planner (`planners.base.Planner`), beside its `horizon`
PLANNER_METHODS = ("initial_mean", "shift", "carry", "warm_start", "plan")


def lacking(planner: object) -> list[str]:
    """The `PLANNER_METHODS` a planner, or its class, does not have."""
    return [m for m in PLANNER_METHODS if not callable(getattr(planner, m, None))]


def register_planner(
    name: str, schema: type | None = None, planner: type | None = None
) -> Callable[[Any], Any]:
    """Decorator: register the decorated builder ``(planner group, System, dtype) -> planner``
    as planner `name`. Given the class it builds (`planner`, or the builder's own ``planner``
    attribute, as `planners.base.sampling_builder`'s has), a class without a method the
    planning policy calls is refused here, a `PluginError` naming it."""

    def add(build: Any) -> Any:
        cls = planner or getattr(build, "planner", None)
        missing = lacking(cls) if cls is not None else []
        if missing:
            raise PluginError(
                f"planner {name!r}: its {cls.__name__} has no {', '.join(missing)}, which the "
                "planning policy calls (the Planner protocol, mbrl_delan/planners/base.py)"
            )
        return PLANNERS.add(name, build, schema)

    return add


# builder: (fit's model config group, fit.InverseContext) -> InverseDynamicsModel
register_inverse_model = INVERSE_MODELS.register


def _none(cfg: Any) -> None:
    return None


def _no_tree(cfg: Any) -> str:
    return f"needs the robot's kinematic tree (an MJCF), which data={cfg.name} does not give"


@dataclass(frozen=True)
class DataKind:
    """A fit's data kind (``python -m mbrl_delan.fit data=NAME``), each function taking the
    config's data group typed by the kind's schema.

    read: the group -> `mbrl_delan.data.inverse_data.InverseData` (reads its files or
        simulates; a bad value or file is a ConfigError, ArrayFormatError or
        FileNotFoundError naming it).
    check: the rules between the group's keys, before anything is read (ConfigError).
    splits: the group -> the names of the splits its data give (``stop_on`` names one).
    tau: what the data's torques are (summary.json's ``tau``).
    summary: the data's provenance -> summary.json's fields naming the data.
    no_tree: the group -> why these data give the models no MJCF tree (a ConfigError's
        message for the models fitted on one, by default that the kind gives none), None
        when they do.
    friction: the group -> the friction kind the data were made with, None when unknown.
    mass_matrix_error: (group, q (N, nq), a model's M (N, nv, nv)) -> the median relative
        error against the system that made the data, where it is known; None: not known.
    """

    read: Callable[[Any], Any]
    check: Callable[[Any], None]
    splits: Callable[[Any], tuple[str, ...]]
    tau: str
    summary: Callable[[Mapping[str, Any]], dict[str, Any]]
    no_tree: Callable[[Any], str | None] = _no_tree
    friction: Callable[[Any], str | None] = _none
    mass_matrix_error: Callable[[Any, Any, Any], float] | None = None


def register_fit_data(name: str, kind: DataKind, schema: type) -> DataKind:
    """Register `kind` as the fit's ``data=name``, its group typed by `schema`."""
    return FIT_DATA.add(name, kind, schema)
