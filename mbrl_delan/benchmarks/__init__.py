"""Benchmark suites, what they share (`BenchSettings`, timing) and the suites by name.

A suite is a function ``(options, bench) -> Iterator[BenchRecord]``: `options` an instance of
the schema of its name in `mbrl_delan.conf.bench_schema.SUITE_SCHEMAS` (its own settings),
`bench` the `BenchSettings` every suite gets. `get_suite` imports it lazily (so listing and
checking suites imports nothing heavy).
"""

from __future__ import annotations

import importlib
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import torch

from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_names import (  # noqa: F401 - the suites' names, re-exported
    COMPILED_SUFFIX,
    FIDELITY_CASES,
    GRAPH_SUFFIX,
    HUMANOID_MODEL_VARIANTS,
    HUMANOID_MODELS,
    HUMANOID_ORACLE_TASKS,
    ILQR_TASKS,
    ORACLE_PLANNERS,
    OWN_ARM_MODELS,
    OWN_ARM_ROBOTS,
    PLANNER_MODELS,
    REALTIME_DYNAMICS,
    REALTIME_TASKS,
    plugin_case,
    split_plugin_case,
)
from mbrl_delan.conf.bench_schema import SUITE_NAMES, SUITE_SCHEMAS  # noqa: F401 - re-exported
from mbrl_delan.provenance import cpu_name

Suite = Callable[[Any, "BenchSettings"], Iterator[BenchRecord]]
# each suite's function, ``module:function``, imported only to run it (its options'
# schema: `mbrl_delan.conf.bench_schema.SUITE_SCHEMAS`, under the same name)
SUITES: dict[str, str] = {
    "delan": "mbrl_delan.benchmarks.delan:run_delan_suite",
    "identify": "mbrl_delan.benchmarks.identify:run_identify_suite",
    "mocap": "mbrl_delan.benchmarks.mocap:run_mocap_suite",
    "identify_humanoid": "mbrl_delan.benchmarks.humanoid_identify:run_identify_humanoid_suite",
    "planner": "mbrl_delan.benchmarks.planner:run_planner_suite",
    "humanoid": "mbrl_delan.benchmarks.humanoid:run_humanoid_suite",
    "realtime": "mbrl_delan.benchmarks.realtime:run_realtime_suite",
    "robust": "mbrl_delan.benchmarks.robust:run_robust_suite",
    "fit_arrays": "mbrl_delan.benchmarks.fit_arrays:run_fit_arrays_suite",
    "soak": "mbrl_delan.benchmarks.soak:run_soak_suite",
    "fidelity": "mbrl_delan.benchmarks.fidelity:run_fidelity_suite",
    "own_arm": "mbrl_delan.benchmarks.own_arm:run_own_arm_suite",
}
C = TypeVar("C")


class UnknownSuiteError(KeyError):
    """The asked suite is not registered; the message lists those that are."""

    def __str__(self) -> str:
        return str(self.args[0])


def get_suite(name: str) -> Suite:
    if name not in SUITES:
        raise UnknownSuiteError(
            f"unknown benchmark suite {name!r}; valid suites: {', '.join(SUITE_NAMES)}"
        )
    module, function = SUITES[name].split(":")
    return getattr(importlib.import_module(module), function)


@dataclass(frozen=True)
class TimingConfig:
    """How each figure is timed.

    `warmup` untimed calls; then the number of calls per measurement k is doubled until k calls
    take at least `min_time_s`; then `repeats` measurements of k calls; the figure is the
    median time per call.
    """

    repeats: int = 5
    min_time_s: float = 0.2
    warmup: int = 2

    def __post_init__(self) -> None:
        if self.repeats < 1 or self.warmup < 0 or self.min_time_s <= 0:
            raise ValueError(f"need repeats >= 1, warmup >= 0, min_time_s > 0, got {self}")


@dataclass
class Timing:
    """The result of timing one callable."""

    seconds_per_call: float  # median over the measurements
    calls_per_measurement: int
    repeats: int
    spread: float  # (slowest - fastest) / median, over the measurements

    def fields(self) -> dict[str, Any]:
        return {
            "seconds_per_call": self.seconds_per_call,
            "calls_per_measurement": self.calls_per_measurement,
            "repeats": self.repeats,
            "spread": self.spread,
        }


@dataclass(frozen=True)
class BenchSettings:
    """What every suite gets beside its own options: where and how its figures are measured."""

    device: torch.device
    timing: TimingConfig = TimingConfig()
    max_call_s: float = 5.0  # skip a figure whose single call is predicted to take longer
    max_memory_bytes: int = 2 * 1024**3  # skip a figure whose main tensors are predicted larger
    quick: bool = False  # tiny sizes: each suite applies its own quick sizes


def with_options(cfg: C, given: dict[str, Any]) -> C:
    """`cfg` (a suite's frozen config) with each of `given` that is not None in place of its
    field of that name; a list (as an options schema holds it) becomes a tuple."""
    set_ = {k: tuple(v) if isinstance(v, list) else v for k, v in given.items() if v is not None}
    return replace(cfg, **set_)


def synchronizer(device: torch.device) -> Callable[[], None]:
    """A function that waits for the device's queued work (a no-op on CPU)."""
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def _timed(fn: Callable[[], object], calls: int, sync: Callable[[], None]) -> float:
    sync()
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    sync()
    return time.perf_counter() - start


def time_call(
    fn: Callable[[], object], cfg: TimingConfig, sync: Callable[[], None] = lambda: None
) -> Timing:
    """Time `fn()` as `TimingConfig` describes."""
    for _ in range(cfg.warmup):
        fn()
    sync()
    calls = 1
    while True:
        elapsed = _timed(fn, calls, sync)
        if elapsed >= cfg.min_time_s:
            break
        grow = cfg.min_time_s / max(elapsed, 1e-9)
        calls = max(2 * calls, min(int(calls * grow * 1.2), 1_000_000))
    samples = [_timed(fn, calls, sync) / calls for _ in range(cfg.repeats)]
    median = statistics.median(samples)
    return Timing(
        seconds_per_call=median,
        calls_per_measurement=calls,
        repeats=cfg.repeats,
        spread=(max(samples) - min(samples)) / median,
    )


def single_call_seconds(fn: Callable[[], object], sync: Callable[[], None]) -> float:
    """Seconds of one call after one untimed call (for predicting whether to skip)."""
    fn()
    return _timed(fn, 1, sync)


def host_fields(device: torch.device) -> dict[str, Any]:
    """Fields every record carries: versions, CPU (and GPU) name, torch threads, time."""
    fields: dict[str, Any] = {
        "threads": torch.get_num_threads(),
        "torch_version": torch.__version__,
        "cpu": cpu_name(),
        "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if device.type == "cuda":
        fields["gpu"] = torch.cuda.get_device_name(device)
    return fields
