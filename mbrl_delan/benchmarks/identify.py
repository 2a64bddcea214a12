"""Suite `identify`: does a DeLaN fitted on MuJoCo data recover MuJoCo's physics?

For each system (pendulum, acrobot, arm2, arm3) a DeLaN with its default network (hidden 64,
2 layers, softplus) and viscous friction only (`coulomb=False`: these MJCFs have no Coulomb
friction) is fitted by its inverse-dynamics loss on `n_samples` random states and controls
with MuJoCo's exact accelerations (`data.synthetic.dynamics_dataset`), then compared with
MuJoCo on `n_test` other random states (a second generator; never used for fitting,
validation or any choice of settings):

- `mass_matrix_rel_error_median`: median over states of ||M_learned - M_mujoco||_F / ||M_mujoco||_F.
- `gravity_rel_error_median`: median of ||g_learned - g_mujoco|| / ||g_mujoco|| over the states
  with ||g_mujoco|| >= 1% of its median (g_mujoco = `qfrc_bias` at zero velocity).
- `damping_rel_error`: max over DoF of |D_learned - D_mjcf| / D_mjcf.
- `torque_r2`: 1 - sum (tau_hat - tau)^2 / sum (tau - mean tau)^2 over states and DoFs, with
  tau_hat = DeLaN's inverse dynamics at MuJoCo's (q, qd, qdd) and tau = B a.
- `passive_energy_drift`: max over `energy_starts` held-out states of |E(T) - E(0)| / E(0) for
  the learned model's own dynamics without dissipation and torque, `energy_steps` RK4 steps
  of `energy_dt`; E = T + V - V_min, with V_min the learned potential's minimum over the
  held-out positions (the learned V has an arbitrary additive constant). Each record also
  carries `mujoco_energy_drift`, the same figure for MuJoCo's own model: the integrator's share.

Fitting: Adam and `fit_model` (validation split, early stopping on the validation loss, best
weights restored) in `stages` stages of falling learning rate (x `lr_decay` per stage), each
allowed an equal share of the epochs left and started from the best weights of the one
before; all stages use the same split. Unactuated DoFs get a torque-error scale of their own
(`DeLaN.unactuated_torque_scale`): large in the first stage, so the actuated equations,
which fix the scale of the Lagrangian, lead the fit out of the M -> 0 basin of the
unactuated DoF's homogeneous equation; then like the actuated ones.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.benchmarks import BenchSettings, host_fields
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import IdentifySuiteConfig
from mbrl_delan.data.synthetic import F64, PassiveMuJoCo, dynamics_dataset, reference_terms
from mbrl_delan.models.delan import DeLaN, Stepping
from mbrl_delan.models.integrators import integrate
from mbrl_delan.models.lagrangian import LagrangianDynamics
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.system import JointLayout, System, load_system
from mbrl_delan.training.fit import FitConfig, FitReport, fit_model
from mbrl_delan.training.schedule import LearningRateStages, run_stages

log = logging.getLogger(__name__)

SUITE = "identify"
SYSTEMS = ("pendulum", "acrobot", "arm2", "arm3")
METRICS = (
    "mass_matrix_rel_error_median",
    "gravity_rel_error_median",
    "damping_rel_error",
    "torque_r2",
    "passive_energy_drift",
)
GRAVITY_FLOOR = 0.01  # states with ||g|| below this fraction of its median are skipped


@dataclass(frozen=True)
class IdentifyConfig:
    """Sizes and training settings of the suite.

    Attributes:
        n_samples: training + validation samples per system (<= 5,000 in the issue).
        n_test: held-out states for every metric.
        max_epochs: epochs over all learning-rate stages together.
        batch_size: samples per minibatch.
        lr: Adam's learning rate in the first stage.
        warmup_steps: the first stage ramps the learning rate linearly from lr / warmup_steps
            to lr over this many optimizer steps (without it, lr 1e-2 collapsed M to 0 on the
            pendulum within an epoch; see `fit_identification`).
        lr_decay: factor on the learning rate from one stage to the next.
        stages: number of learning-rate stages; each gets an equal share of the epochs left.
        patience: epochs without a better validation loss that end a stage early.
        val_fraction: share of `n_samples` used for validation (early stopping).
        dtype: the model's and the data's float type.
        coulomb: learn Coulomb friction too (MuJoCo's systems here have none).
        unactuated_scales: torque-error scale of an unactuated DoF, in units of the largest
            actuated DoF's torque std, per stage (the last one for the stages after; see
            `DeLaN.unactuated_torque_scale`).
        q_scale, qd_scale: states are uniform in [-q_scale, q_scale] x [-qd_scale, qd_scale].
        energy_starts, energy_steps, energy_dt: the passive energy-drift rollout.
        seed: seeds the network's initial weights, the data and the split.
        systems: MJCF asset names.
    """

    n_samples: int = 5000
    n_test: int = 1000
    max_epochs: int = 500
    batch_size: int = 128
    lr: float = 1e-2
    warmup_steps: int = 200
    lr_decay: float = 0.3
    stages: int = 4
    patience: int = 50
    val_fraction: float = 0.1
    dtype: torch.dtype = torch.float64
    coulomb: bool = False
    unactuated_scales: tuple[float, ...] = (10.0, 1.0)
    q_scale: float = math.pi
    qd_scale: float = 2.0 * math.pi
    energy_starts: int = 16
    energy_steps: int = 1000
    energy_dt: float = 0.005
    seed: int = 0
    systems: tuple[str, ...] = SYSTEMS

    def __post_init__(self) -> None:
        if self.n_samples < 2 or self.n_test < 1 or self.max_epochs < 1 or self.stages < 1:
            raise ValueError(f"need n_samples >= 2, n_test, max_epochs, stages >= 1: {self}")
        if not 1 <= self.energy_starts <= self.n_test:
            raise ValueError("energy_starts must be in [1, n_test]")
        if not self.unactuated_scales or min(self.unactuated_scales) <= 0:
            raise ValueError(f"unactuated_scales must be > 0, got {self.unactuated_scales}")

    def schedule(self) -> LearningRateStages:
        """The learning-rate stages of the fit."""
        return LearningRateStages(
            lr=self.lr,
            stages=self.stages,
            decay=self.lr_decay,
            warmup_steps=self.warmup_steps,
            max_epochs=self.max_epochs,
        )

    def unactuated_scale(self, stage: int) -> float:
        """The unactuated DoFs' torque-error scale in stage `stage` (from 0)."""
        return self.unactuated_scales[min(stage, len(self.unactuated_scales) - 1)]

    @classmethod
    def quick(cls, **overrides: Any) -> IdentifyConfig:
        """Tiny sizes for tests and smoke runs (seconds for all four systems)."""
        sizes = dict(
            n_samples=64,
            n_test=32,
            max_epochs=2,
            batch_size=32,
            stages=2,
            patience=1,
            energy_starts=4,
            energy_steps=10,
        )
        return cls(**{**sizes, **overrides})


# ----------------------------------------------------------------------------- fitting


def make_model(system: System, cfg: IdentifyConfig) -> DeLaN:
    """DeLaN with the default network, inverse loss, viscous (and optionally Coulomb) friction."""
    torch.manual_seed(cfg.seed)
    model = DeLaN(
        system.layout,
        system.actuation,
        control_dt=system.control_dt,
        structure=Structure(coulomb=cfg.coulomb),
        stepping=Stepping(loss="inverse", unactuated_torque_scale=cfg.unactuated_scale(0)),
    )
    return model.to(cfg.dtype)


@dataclass
class IdentifyFit:
    """A fitted model and how the fit went."""

    model: DeLaN
    reports: list[FitReport]  # one per learning-rate stage
    seconds: float

    @property
    def epochs(self) -> int:
        return sum(r.epochs_run for r in self.reports)

    @property
    def best_val_loss(self) -> float:
        return self.reports[-1].best_val_loss


def fit_identification(model: DeLaN, data: TensorDict, cfg: IdentifyConfig) -> IdentifyFit:
    """Fit `model` on `data` (N,) by `fit_model` in the stages of `cfg.schedule()`
    (`mbrl_delan.training.schedule`: falling lr, a linear warm-up first).

    Each stage ends early after `cfg.patience` epochs without a better validation loss and
    starts from the best weights of the stage before. Every stage splits with the same seed,
    so the validation samples never enter training.
    """
    start = time.perf_counter()
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    reports: list[FitReport] = []

    def fit_stage(stage: int, epochs: int) -> int:
        model.unactuated_torque_scale = cfg.unactuated_scale(stage)
        fit_cfg = FitConfig(
            batch_size=cfg.batch_size,
            max_epochs=epochs,
            val_fraction=cfg.val_fraction,
            patience=cfg.patience,
        )
        report = fit_model(model, optimizer, data, fit_cfg, torch.Generator().manual_seed(cfg.seed))
        reports.append(report)
        log.info(
            "stage %d (lr %.2g): %d epochs, best validation loss %.3g",
            stage,
            optimizer.param_groups[0]["lr"],
            report.epochs_run,
            report.best_val_loss,
        )
        return report.epochs_run

    run_stages(optimizer, cfg.schedule(), fit_stage)
    return IdentifyFit(model=model, reports=reports, seconds=time.perf_counter() - start)


# ----------------------------------------------------------------------------- metrics


@dataclass
class IdentifyMetrics:
    """The suite's figures for one fitted model (see the module docstring)."""

    mass_matrix_rel_error_median: float
    gravity_rel_error_median: float
    damping_rel_error: float
    torque_r2: float
    passive_energy_drift: float
    details: dict[str, Any] = field(default_factory=dict)  # per-DoF and secondary figures

    def values(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in METRICS}


def relative_errors(learned: Tensor, reference: Tensor) -> Tensor:
    """||learned - reference|| / ||reference|| per sample, Frobenius over the trailing dims.

    (N, ...) , (N, ...) -> (N,)
    """
    dims = tuple(range(1, reference.dim()))
    return (learned - reference).norm(dim=dims) / reference.norm(dim=dims)


def gravity_errors(learned: Tensor, reference: Tensor, floor: float = GRAVITY_FLOOR) -> Tensor:
    """Relative errors of g (N, n) over the states whose ||g_ref|| >= floor * its median. (M,)"""
    norms = reference.norm(dim=-1)
    keep = norms >= floor * norms.median()
    return relative_errors(learned[keep], reference[keep])


def torque_r2(predicted: Tensor, target: Tensor) -> float:
    """1 - SSE / SST pooled over samples and DoFs (SST around each DoF's mean). (N, n) each."""
    sse = (predicted - target).pow(2).sum()
    sst = (target - target.mean(dim=0)).pow(2).sum()
    return float(1.0 - sse / sst)


Field = Callable[[Tensor, Tensor], Tensor]  # (q (S, nq), qd (S, nv)) -> (S, ...)


def energy_drift(
    layout: JointLayout,
    acceleration: Field,
    energy: Field,
    q0: Tensor,
    qd0: Tensor,
    v_min: Tensor | float,
    steps: int,
    dt: float,
) -> Tensor:
    """|E(T) - E(0)| / E(0) per start state, E = energy - v_min, after `steps` RK4 steps of dt.

    `acceleration` and `energy` take (S, nq), (S, nv) and give (S, nv) and (S,). -> (S,)
    """
    e0 = energy(q0, qd0) - v_min
    q, qd = q0, qd0
    for _ in range(steps):
        state = integrate(layout, acceleration, q, qd, dt, "rk4")
        q, qd = state.q, state.qd
    return (energy(q, qd) - v_min - e0).abs() / e0


def passive_energy_drift(
    model: DeLaN, q0: Tensor, qd0: Tensor, q_rest: Tensor, steps: int, dt: float
) -> Tensor:
    """`energy_drift` of the learned model without dissipation and torque. (S,)

    E = T + V - V_min with V_min the learned V's minimum over q_rest (N, nq) and q0 (S, nq).
    """
    conservative = LagrangianDynamics(
        model.dynamics.field, None, model.dynamics.actuation, model.dynamics.rotational_dofs
    )

    def acceleration(q: Tensor, qd: Tensor) -> Tensor:
        return conservative.forward_dynamics(q, qd, torch.zeros_like(qd))

    def energy(q: Tensor, qd: Tensor) -> Tensor:
        terms = conservative.terms(q, qd)
        return terms.kinetic_energy + terms.potential_energy

    with torch.no_grad():
        q_all = torch.cat([q_rest, q0])
        v_min = conservative.terms(q_all, q_all.new_zeros(q_all.shape[0], qd0.shape[-1]))
        v_min = v_min.potential_energy.min()
        return energy_drift(model.layout, acceleration, energy, q0, qd0, v_min, steps, dt)


def mujoco_energy_drift(
    system: System, q0: Tensor, qd0: Tensor, q_rest: Tensor, steps: int, dt: float
) -> Tensor:
    """The same figure for MuJoCo's own model (damping off): the integrator's share. (S,)"""
    passive = PassiveMuJoCo(system)
    q0, qd0, q_all = (x.detach().cpu().double() for x in (q0, qd0, torch.cat([q_rest, q0])))
    v_min = passive.energy(q_all, torch.zeros(q_all.shape[0], system.nv, dtype=F64)).min()
    return energy_drift(
        system.layout, passive.acceleration, passive.energy, q0, qd0, v_min, steps, dt
    )


def evaluate_identification(
    model: DeLaN, system: System, test: TensorDict, cfg: IdentifyConfig
) -> IdentifyMetrics:
    """Compare the fitted model with MuJoCo on the held-out data `test` (N,)."""
    q, qd, qdd, tau = (test[k].to(cfg.dtype) for k in (keys.Q, keys.QD, keys.QDD, keys.TAU))
    reference = reference_terms(system, q)
    with torch.no_grad():
        terms = model.terms(q, torch.zeros_like(qd))
        tau_hat = model.dynamics.inverse_dynamics(q, qd, qdd)
    m_err = relative_errors(terms.mass_matrix, reference.mass_matrix.to(cfg.dtype))
    g_err = gravity_errors(terms.gravity, reference.gravity.to(cfg.dtype))
    learned_d, true_d = _viscous(model), system.damping.to(cfg.dtype)
    drift = passive_energy_drift(
        model, q[: cfg.energy_starts], qd[: cfg.energy_starts], q, cfg.energy_steps, cfg.energy_dt
    )
    reference_drift = mujoco_energy_drift(
        system, q[: cfg.energy_starts], qd[: cfg.energy_starts], q, cfg.energy_steps, cfg.energy_dt
    )
    return IdentifyMetrics(
        mass_matrix_rel_error_median=float(m_err.median()),
        gravity_rel_error_median=float(g_err.median()),
        damping_rel_error=float(((learned_d - true_d).abs() / true_d).max()),
        torque_r2=torque_r2(tau_hat, tau),
        passive_energy_drift=float(drift.max()),
        details=dict(
            mass_matrix_rel_error_p90=float(m_err.quantile(0.9)),
            gravity_rel_error_p90=float(g_err.quantile(0.9)),
            gravity_states=int(g_err.numel()),
            damping_learned=learned_d.tolist(),
            damping_mjcf=true_d.tolist(),
            mujoco_energy_drift=float(reference_drift.max()),
        ),
    )


def _viscous(model: DeLaN) -> Tensor:
    """The learned viscous damping per DoF (n,); zeros when the model has no dissipation."""
    dissipation = model.dynamics.dissipation
    if dissipation is None:
        return torch.zeros(model.layout.nv)
    return dissipation.viscous.detach()


# ----------------------------------------------------------------------------- the suite


UNIT = "fraction"  # every metric of the suite is a ratio


def identify_system(name: str, cfg: IdentifyConfig) -> tuple[IdentifyFit, IdentifyMetrics]:
    """Data, fit and metrics for one system."""
    system = load_system(name)
    data = dynamics_dataset(
        system,
        cfg.n_samples,
        torch.Generator().manual_seed(cfg.seed),
        q_scale=cfg.q_scale,
        qd_scale=cfg.qd_scale,
    )
    test = dynamics_dataset(
        system,
        cfg.n_test,
        torch.Generator().manual_seed(cfg.seed + 10_000),
        q_scale=cfg.q_scale,
        qd_scale=cfg.qd_scale,
    )
    model = make_model(system, cfg)
    fit = fit_identification(model, data.to(cfg.dtype), cfg)
    return fit, evaluate_identification(fit.model, system, test, cfg)


def run_identify(cfg: IdentifyConfig) -> Iterator[BenchRecord]:
    """Records of every metric for every system in `cfg.systems`, computed on the CPU."""
    device = "cpu"
    host = host_fields(torch.device(device))
    for name in cfg.systems:
        fit, metrics = identify_system(name, cfg)
        fields = dict(
            system=name,
            dof=fit.model.layout.nv,
            n_samples=cfg.n_samples,
            n_test=cfg.n_test,
            dtype=str(cfg.dtype).removeprefix("torch."),
            epochs=fit.epochs,
            best_val_loss=fit.best_val_loss,
            fit_seconds=fit.seconds,
            coulomb=cfg.coulomb,
            **metrics.details,
            **host,
        )
        log.info("%s: %s (%d epochs, %.0f s)", name, metrics.values(), fit.epochs, fit.seconds)
        for metric, value in metrics.values().items():
            yield BenchRecord(SUITE, name, metric, value, UNIT, device, dict(fields))


def suite_config(options: IdentifySuiteConfig, quick: bool = False) -> IdentifyConfig:
    """The suite's config: `IdentifyConfig.quick()` under `quick`, else the defaults; then
    the options' `n_samples` and `max_epochs` where they are not None."""
    cfg = IdentifyConfig.quick() if quick else IdentifyConfig()
    overrides = {
        name: value
        for name, value in (("n_samples", options.n_samples), ("max_epochs", options.max_epochs))
        if value is not None
    }
    return replace(cfg, **overrides)


def run_identify_suite(options: IdentifySuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """The registered suite: `run_identify` with `suite_config`, on the CPU."""
    if bench.device.type != "cpu":
        log.warning("suite identify runs on the CPU (asked for %s)", bench.device)
    yield from run_identify(suite_config(options, bench.quick))
