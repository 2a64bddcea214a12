"""Suite `identify_humanoid`: DeLaN fitted to a floating-base humanoid's inverse dynamics.

For gymnasium's Humanoid-v5 model (free root + 17 hinges, nv = 23) and dm_control's CMU
humanoid (free root + 56 hinges, nv = 62), loaded with plain mujoco, contacts and joint and
tendon limits disabled (`mbrl_delan.data.synthetic.inverse_dynamics_dataset`):

1. Data: `n_samples` random states and accelerations, q with a uniformly random root
   orientation and hinges uniform in their ranges, qd ~ N(0, 1), qdd ~ N(0, 5^2) per DoF,
   tau = `mj_inverse` (all nv generalized forces, the root's 6 included); `n_test` held-out
   samples from a second seed, used by the metrics only.
2. Model: `DeLaN` with B = I (tau is learned directly), `loss='inverse'`, viscous friction,
   `inertia_scaling` (units of M, V and friction from the data: the root's 40 kg and the
   wrists' 0.02 kg m^2 differ by 10^3) and `diagonal_init`.
3. Fit: `fit_identification` (Adam in learning-rate stages with early stopping), float32.

Metrics (record `case` = system): `torque_r2` (pooled over DoFs, as suite identify),
`mass_matrix_rel_error_median`, `gravity_rel_error_median` (against `mj_fullM` and
`qfrc_bias` at qd = 0) and `damping_rel_error` (max over the DoFs with MJCF damping > 0).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.benchmarks import BenchSettings, host_fields
from mbrl_delan.benchmarks.identify import (
    IdentifyConfig,
    fit_identification,
    gravity_errors,
    relative_errors,
    torque_r2,
)
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import IdentifySuiteConfig
from mbrl_delan.data.synthetic import inverse_dynamics_dataset, reference_terms
from mbrl_delan.models.delan import DeLaN, Stepping
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.external import humanoid_cmu_xml, humanoid_v5_xml
from mbrl_delan.systems.system import System, load_system

log = logging.getLogger(__name__)

SUITE = "identify_humanoid"
MODELS: dict[str, Callable[[], Path]] = {
    "humanoid": humanoid_v5_xml,
    "humanoid_cmu": humanoid_cmu_xml,
}


@dataclass(frozen=True)
class HumanoidIdentifyConfig:
    """Sizes and settings (the defaults reach torque R^2 >= 0.98 on Humanoid-v5).

    `fit` holds the training settings shared with suite identify (`IdentifyConfig`: epochs,
    batch, learning-rate stages, patience, dtype, seed); its state-sampling fields are unused.
    """

    n_samples: int = 30_000
    n_test: int = 1_000
    hidden: int = 128
    layers: int = 2
    qd_scale: float = 1.0
    qdd_scale: float = 5.0
    fit: IdentifyConfig = IdentifyConfig(
        max_epochs=100, batch_size=256, patience=30, dtype=torch.float32, n_test=16
    )
    systems: tuple[str, ...] = tuple(MODELS)
    compile: bool = True  # fit through the compiled loss (`mbrl_delan.accelerate.compile_fit`)

    @classmethod
    def quick(cls) -> HumanoidIdentifyConfig:
        """Seconds: 256 samples, 2 epochs, Humanoid-v5 only, eager (for tests of the plumbing)."""
        fit = replace(cls.fit, max_epochs=2, stages=1, patience=2, batch_size=64)
        return cls(
            n_samples=256, n_test=64, hidden=16, fit=fit, systems=("humanoid",), compile=False
        )


@dataclass
class HumanoidIdentification:
    """A fitted model and its figures on the held-out samples."""

    model: DeLaN
    metrics: dict[str, float]
    seconds: float
    epochs: int


def humanoid_system(name: str) -> System:
    """The MJCF of `name` (a key of `MODELS`) as a `System`."""
    if name not in MODELS:
        raise ValueError(f"unknown humanoid {name!r}; choose one of {', '.join(MODELS)}")
    return load_system(MODELS[name](), name=name)


def make_model(system: System, cfg: HumanoidIdentifyConfig) -> DeLaN:
    torch.manual_seed(cfg.fit.seed)
    model = DeLaN(
        system.layout,
        torch.eye(system.nv, dtype=torch.float64),
        control_dt=system.control_dt,
        structure=Structure(
            hidden=cfg.hidden,
            layers=cfg.layers,
            coulomb=False,
            inertia_scaling=True,
            diagonal_init=True,
        ),
        stepping=Stepping(loss="inverse"),
    ).to(cfg.fit.dtype)
    if cfg.compile:
        compile_fit(model)
    return model


def _data(system: System, n: int, seed: int, cfg: HumanoidIdentifyConfig) -> TensorDict:
    generator = torch.Generator().manual_seed(seed)
    data = inverse_dynamics_dataset(
        system, n, generator, qd_scale=cfg.qd_scale, qdd_scale=cfg.qdd_scale
    )
    return data.to(cfg.fit.dtype)


def evaluate(model: DeLaN, system: System, test: TensorDict) -> dict[str, float]:
    """The suite's metrics of a fitted model on held-out samples (module docstring)."""
    q, qd, qdd, tau = (test[k] for k in (keys.Q, keys.QD, keys.QDD, keys.TAU))
    reference = reference_terms(system, q)
    with torch.no_grad():
        tau_hat = model.dynamics.inverse_dynamics(q, qd, qdd)
        terms = model.terms(q, torch.zeros_like(qd))
        viscous = model.dynamics.dissipation.viscous
    damped = system.damping > 0
    true_d = system.damping[damped].to(viscous.dtype)
    return {
        "torque_r2": torque_r2(tau_hat.double(), tau.double()),
        "mass_matrix_rel_error_median": float(
            relative_errors(terms.mass_matrix.double(), reference.mass_matrix).median()
        ),
        "gravity_rel_error_median": float(
            gravity_errors(terms.gravity.double(), reference.gravity).median()
        ),
        "damping_rel_error": float(((viscous[damped] - true_d).abs() / true_d).max()),
    }


def identify_humanoid(name: str, cfg: HumanoidIdentifyConfig) -> HumanoidIdentification:
    """Data, fit and metrics for one humanoid."""
    system = humanoid_system(name)
    data = _data(system, cfg.n_samples, cfg.fit.seed, cfg)
    test = _data(system, cfg.n_test, cfg.fit.seed + 10_000, cfg)
    start = time.perf_counter()
    fit = fit_identification(make_model(system, cfg), data, cfg.fit)
    seconds = time.perf_counter() - start
    return HumanoidIdentification(fit.model, evaluate(fit.model, system, test), seconds, fit.epochs)


def suite_config(options: IdentifySuiteConfig, quick: bool = False) -> HumanoidIdentifyConfig:
    """Quick sizes under `quick`; the options' `n_samples` and `max_epochs` override."""
    cfg = HumanoidIdentifyConfig.quick() if quick else HumanoidIdentifyConfig()
    if options.n_samples is not None:
        cfg = replace(cfg, n_samples=options.n_samples)
    if options.max_epochs is not None:
        cfg = replace(cfg, fit=replace(cfg.fit, max_epochs=options.max_epochs))
    return cfg


def run_identify_humanoid_suite(
    options: IdentifySuiteConfig, bench: BenchSettings
) -> Iterator[BenchRecord]:
    """The registered suite: every metric for every humanoid, on the CPU."""
    cfg = suite_config(options, bench.quick)
    host = host_fields(torch.device("cpu"))
    for name in cfg.systems:
        result = identify_humanoid(name, cfg)
        fields = dict(
            system=name,
            dof=result.model.layout.nv,
            n_samples=cfg.n_samples,
            n_test=cfg.n_test,
            hidden=cfg.hidden,
            layers=cfg.layers,
            dtype=str(cfg.fit.dtype).removeprefix("torch."),
            epochs=result.epochs,
            fit_seconds=result.seconds,
            **host,
        )
        log.info("%s: %s (%d epochs, %.0f s)", name, result.metrics, result.epochs, result.seconds)
        for metric, value in result.metrics.items():
            yield BenchRecord(SUITE, name, metric, value, "fraction", "cpu", dict(fields))
