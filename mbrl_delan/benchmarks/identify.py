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
  held-out positions (the learned V has an arbitrary additive constant).

Fitting: `fit_model` (validation split, early stopping on the validation loss, best weights
restored) in stages of falling learning rate: each stage runs until early stopping, then the
learning rate is multiplied by `lr_decay` and the next stage starts from the best weights.
All stages use the same split (the split generator is re-seeded).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.benchmarks import SuiteOptions, host_fields
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.data.synthetic import dynamics_dataset, reference_terms
from mbrl_delan.models.delan import DeLaN, LagrangianDynamics
from mbrl_delan.models.integrators import integrate
from mbrl_delan.systems.system import System, load_system
from mbrl_delan.training.fit import FitConfig, FitReport, fit_model

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
        lr_decay: factor on the learning rate from one stage to the next.
        stages: number of learning-rate stages.
        patience: epochs without a better validation loss that end a stage.
        val_fraction: share of `n_samples` used for validation (early stopping).
        dtype: the model's and the data's float type.
        coulomb: learn Coulomb friction too (MuJoCo's systems here have none).
        q_scale, qd_scale: states are uniform in [-q_scale, q_scale] x [-qd_scale, qd_scale].
        energy_starts, energy_steps, energy_dt: the passive energy-drift rollout.
        seed: seeds the network's initial weights, the data and the split.
        systems: MJCF asset names.
    """

    n_samples: int = 5000
    n_test: int = 1000
    max_epochs: int = 3000
    batch_size: int = 128
    lr: float = 3e-3
    lr_decay: float = 0.2
    stages: int = 4
    patience: int = 40
    val_fraction: float = 0.1
    dtype: torch.dtype = torch.float64
    coulomb: bool = False
    loss: str = "inverse"
    warmup_loss: str = "forward"
    warmup_epochs: int = 30
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
        if self.energy_starts > self.n_test:
            raise ValueError("energy_starts must not exceed n_test")

    @classmethod
    def quick(cls, **overrides: Any) -> IdentifyConfig:
        """Tiny sizes for tests and smoke runs (seconds for all four systems)."""
        sizes = dict(
            n_samples=64, n_test=32, max_epochs=2, batch_size=32, stages=1, patience=1,
            energy_starts=4, energy_steps=10,
        )
        return cls(**{**sizes, **overrides})


# ----------------------------------------------------------------------------- fitting


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


class IdentificationDeLaN(DeLaN):
    """DeLaN whose torque-error scale of an unactuated DoF is the largest actuated one.

    DeLaN's per-DoF scale is the torque's std with a floor of 1% of the largest; a DoF without
    actuator (the acrobot's shoulder) has tau = 0 always, so its error would weigh 10^4 times
    more than the others and the fit drifts to the trivial M -> 0, g -> 0 that satisfies its
    homogeneous equation. Its generalized forces are of the size of the actuated ones.
    """

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        super().fit_normalization(data)
        unactuated = self.dynamics.actuation.abs().sum(dim=-1) == 0
        if unactuated.any() and not unactuated.all():
            self.tau_scale[unactuated] = self.tau_scale[~unactuated].max()


def make_model(system: System, cfg: IdentifyConfig) -> DeLaN:
    """DeLaN with the default network, inverse loss, viscous (and optionally Coulomb) friction."""
    torch.manual_seed(cfg.seed)
    model = IdentificationDeLaN(
        system.layout,
        system.actuation,
        control_dt=system.control_dt,
        loss=cfg.loss,
        coulomb=cfg.coulomb,
    )
    return model.to(cfg.dtype)


def fit_identification(model: DeLaN, data: TensorDict, cfg: IdentifyConfig) -> IdentifyFit:
    """Fit `model` on `data` (N,) with `fit_model` in `cfg.stages` stages of falling lr."""
    start = time.perf_counter()
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    reports: list[FitReport] = []
    remaining, lr = cfg.max_epochs, cfg.lr
    if _underactuated(model) and cfg.warmup_epochs > 0:
        loss_kind, model.loss_kind = model.loss_kind, cfg.warmup_loss
        fit_cfg = FitConfig(batch_size=cfg.batch_size, max_epochs=cfg.warmup_epochs,
                            val_fraction=cfg.val_fraction, patience=None)
        report = fit_model(model, optimizer, data, fit_cfg, torch.Generator().manual_seed(cfg.seed + 1))
        log.info("warm-up (%s loss): %d epochs, val loss %.3g", cfg.warmup_loss, report.epochs_run, report.best_val_loss)
        model.loss_kind = loss_kind
        reports.append(report)
        remaining -= report.epochs_run
    for stage in range(cfg.stages):
        if remaining <= 0:
            break
        for group in optimizer.param_groups:
            group["lr"] = lr
        fit_cfg = FitConfig(
            batch_size=cfg.batch_size,
            max_epochs=remaining,
            val_fraction=cfg.val_fraction,
            patience=cfg.patience,
        )
        # The same seed every stage: the same train/validation split.
        generator = torch.Generator().manual_seed(cfg.seed + 1)
        report = fit_model(model, optimizer, data, fit_cfg, generator)
        reports.append(report)
        remaining -= report.epochs_run
        log.info("stage %d (lr %.2g): %d epochs, best val loss %.3g",
                 stage, lr, report.epochs_run, report.best_val_loss)
        lr *= cfg.lr_decay
    return IdentifyFit(model=model, reports=reports, seconds=time.perf_counter() - start)


def _underactuated(model: DeLaN) -> bool:
    return bool((model.dynamics.actuation.abs().sum(dim=-1) == 0).any())


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


def _rest_potential(dynamics: LagrangianDynamics, q: Tensor) -> Tensor:
    """The learned potential's minimum over positions q (N, nq). ()"""
    with torch.no_grad():
        return dynamics.terms(q, torch.zeros(q.shape[0], dynamics.actuation.shape[0],
                                             dtype=q.dtype)).potential_energy.min()


def passive_energy_drift(
    model: DeLaN, q0: Tensor, qd0: Tensor, q_rest: Tensor, steps: int, dt: float
) -> Tensor:
    """|E(T) - E(0)| / E(0) per start state, with E = T + V - V_min. (S,)

    The learned field without dissipation and torque, integrated by RK4 for `steps` steps of
    `dt` from (q0, qd0) (S, nq), (S, nv); V_min is the learned V's minimum over q_rest (N, nq).
    """
    conservative = LagrangianDynamics(
        model.dynamics.field, None, model.dynamics.actuation, model.dynamics.rotational_dofs
    )
    zero_tau = torch.zeros_like(qd0)

    def accel(q: Tensor, qd: Tensor) -> Tensor:
        return conservative.forward_dynamics(q, qd, zero_tau)

    def energy(q: Tensor, qd: Tensor) -> Tensor:
        terms = conservative.terms(q, qd)
        return terms.kinetic_energy + terms.potential_energy

    with torch.no_grad():
        v_min = _rest_potential(conservative, torch.cat([q_rest, q0]))
        e0 = energy(q0, qd0) - v_min
        q, qd = q0, qd0
        for _ in range(steps):
            state = integrate(model.layout, accel, q, qd, dt, "rk4")
            q, qd = state.q, state.qd
        e1 = energy(q, qd) - v_min
    return (e1 - e0).abs() / e0


def evaluate_identification(
    model: DeLaN, system: System, test: TensorDict, cfg: IdentifyConfig
) -> IdentifyMetrics:
    """Compare the fitted model with MuJoCo on the held-out data `test` (N,)."""
    q, qd, qdd, tau = (test[k].to(cfg.dtype) for k in (keys.Q, keys.QD, keys.QDD, keys.TAU))
    reference = reference_terms(system, q)
    with torch.no_grad():
        terms = model.terms(q, torch.zeros_like(qd))
    tau_hat = model.dynamics.inverse_dynamics(q, qd, qdd).detach()
    m_err = relative_errors(terms.mass_matrix, reference.mass_matrix.to(cfg.dtype))
    g_err = gravity_errors(terms.gravity, reference.gravity.to(cfg.dtype))
    learned_d, true_d = _viscous(model), system.damping.to(cfg.dtype)
    drift = passive_energy_drift(
        model, q[: cfg.energy_starts], qd[: cfg.energy_starts], q, cfg.energy_steps, cfg.energy_dt
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
        ),
    )


def _viscous(model: DeLaN) -> Tensor:
    """The learned viscous damping per DoF (n,); zeros when the model has no dissipation."""
    dissipation = model.dynamics.dissipation
    if dissipation is None:
        return torch.zeros(model.layout.nv)
    return dissipation.viscous.detach()


# ----------------------------------------------------------------------------- the suite


UNITS = {
    "mass_matrix_rel_error_median": "fraction",
    "gravity_rel_error_median": "fraction",
    "damping_rel_error": "fraction",
    "torque_r2": "fraction",
    "passive_energy_drift": "fraction",
}


def identify_system(name: str, cfg: IdentifyConfig) -> tuple[IdentifyFit, IdentifyMetrics]:
    """Data, fit and metrics for one system."""
    system = load_system(name)
    data = dynamics_dataset(system, cfg.n_samples, torch.Generator().manual_seed(cfg.seed),
                            q_scale=cfg.q_scale, qd_scale=cfg.qd_scale)
    test = dynamics_dataset(system, cfg.n_test, torch.Generator().manual_seed(cfg.seed + 10_000),
                            q_scale=cfg.q_scale, qd_scale=cfg.qd_scale)
    model = make_model(system, cfg)
    fit = fit_identification(model, data.to(cfg.dtype), cfg)
    return fit, evaluate_identification(fit.model, system, test, cfg)


def run_identify(cfg: IdentifyConfig, device: str = "cpu") -> Iterator[BenchRecord]:
    """Records of every metric for every system in `cfg.systems` (CPU only)."""
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
            yield BenchRecord(SUITE, name, metric, value, UNITS[metric], device, dict(fields))


def suite_config(opts: SuiteOptions) -> IdentifyConfig:
    """The suite's config from the bench options: `quick`, `n_samples`, `max_epochs` when
    `SuiteOptions` carries them (unset or None: the defaults)."""
    quick = bool(getattr(opts, "quick", False))
    cfg = IdentifyConfig.quick() if quick else IdentifyConfig()
    overrides = {
        name: getattr(opts, name)
        for name in ("n_samples", "max_epochs")
        if getattr(opts, name, None) is not None
    }
    return replace(cfg, **overrides)


def run_identify_suite(opts: SuiteOptions) -> Iterator[BenchRecord]:
    """The registered suite: `run_identify` with `suite_config(opts)`, on the CPU."""
    if opts.device.type != "cpu":
        log.warning("suite identify runs on the CPU (asked for %s)", opts.device)
    yield from run_identify(suite_config(opts))
