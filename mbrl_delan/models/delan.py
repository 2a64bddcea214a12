"""DeLaN: a world model over the Lagrangian equations (`mbrl_delan.models.lagrangian`).

Its mechanics come from a `Structure` (`mbrl_delan.models.structure`); this module holds the
model: the control step, the losses and the units taken from data.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput, RigidBody, WorldModel
from mbrl_delan.models.contact import (
    ContactModel,
    ImplicitTerms,
    JointLimits,
    implicit_acceleration,
)
from mbrl_delan.models.features import rotation_matrix
from mbrl_delan.models.field import SPRING_UNITS, LagrangianNetwork
from mbrl_delan.models.integrators import INTEGRATORS, integrate
from mbrl_delan.models.lagrangian import (
    LagrangianTerms,
    from_root_frame,
    to_root_frame,
)
from mbrl_delan.models.structure import Structure
from mbrl_delan.models.tree import RigidBodyTree, TreeDynamics
from mbrl_delan.systems.forward_kinematics import Frames
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import JointLayout, State

LOSSES = ("forward", "inverse", "both")
# the batch entries a per-transition loss reads (`DeLaN.transition_losses`; absent: None)
LOSS_INPUTS = {
    "q": keys.Q,
    "qd": keys.QD,
    "action": keys.ACTION,
    "qdd": keys.QDD,
    "next_q": keys.NEXT_Q,
    "next_qd": keys.NEXT_QD,
}


CONSTANT_RATIO = 1e-6  # a per-DoF spread below this fraction of the largest: not varying


def _is_mechanics(key: str) -> bool:
    """A state-dict entry of the Lagrangian part (M, V, friction), not the actuation B."""
    return key.startswith("dynamics.") and key != "dynamics.actuation"


def _varies(spread: Tensor) -> Tensor:
    """(n,) bool: spread_i >= CONSTANT_RATIO * max(spread) and > 0."""
    return (spread > 0) & (spread >= CONSTANT_RATIO * spread.max())


def _fill_geometric(units: Tensor, known: Tensor) -> Tensor:
    """units where known, the geometric mean of the known ones elsewhere. (n,)"""
    fill = units[known].log().mean().exp()
    return torch.where(known, units, fill)


def _scale(x: Tensor, floor_ratio: float = 1e-2) -> Tensor:
    """Per-column std with a floor relative to the largest (unactuated DoFs have std 0)."""
    std = x.std(dim=0) if x.shape[0] > 1 else x.abs().mean(dim=0)
    return std.clamp_min(floor_ratio * float(std.max().clamp_min(1e-8)))


def _needed(value: Tensor | None, key: str | tuple[str, ...]) -> Tensor:
    """A loss input the batch must hold."""
    if value is None:
        raise KeyError(f"the loss needs {key!r} in the batch")
    return value


@dataclass(frozen=True)
class Stepping:
    """How a DeLaN steps and what it learns from, beside what it is made of (`Structure`).

    integrator: ``euler`` (semi-implicit) or ``rk4``, `substeps` steps per control step.
    loss: ``forward`` (the integrated next state), ``inverse`` (the torque) or ``both``.
    unactuated_torque_scale: an unactuated DoF's torque error normalised by this times the
    largest actuated std. velocity_margin: the velocity limit is this times the largest |qd|
    in the data (`max_velocity` before any data)."""

    integrator: str = "rk4"
    substeps: int = 1
    loss: str = "forward"
    unactuated_torque_scale: float = 1.0
    velocity_margin: float = 3.0
    max_velocity: float = 100.0

    def __post_init__(self) -> None:
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {self.integrator!r}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if self.substeps < 1:
            raise ValueError(f"need substeps >= 1, got {self.substeps}")
        if min(self.unactuated_torque_scale, self.velocity_margin, self.max_velocity) <= 0:
            raise ValueError(
                "need unactuated_torque_scale, velocity_margin, max_velocity > 0, got "
                f"{self.unactuated_torque_scale}, {self.velocity_margin}, {self.max_velocity}"
            )


@dataclass(frozen=True)
class TreePrior:
    """The known kinematic tree's rigid body (`RigidBodyTree`) a DeLaN stands on: with
    `residual`, the networks' mechanics a residual Lagrangian beside it (`TreeDynamics`),
    whose share of the inverse-dynamics torque the loss adds times `penalty`."""

    tree: RigidBodyTree
    residual: bool = False
    penalty: float = 0.0

    def __post_init__(self) -> None:
        if self.penalty < 0 or (self.penalty > 0 and not self.residual):
            raise ValueError(
                f"residual_penalty must be >= 0 and needs a tree residual, got {self.penalty}"
            )


class DeLaN(WorldModel):
    """DeLaN world model: the Lagrangian equations over networks, stepped by an integrator.

    What the mechanics are made of (network size, friction, invariances, tree sparsity,
    armature, units from data, a residual force) is the frozen `structure`; see
    `Structure` for each option. `contact`: a structured contact force beside them
    (`ContactModel`: points of the body tree on the floor, in SI units), taken at the end of
    each integrator step with the model's own M when it is `implicit`
    (`models.contact.implicit_acceleration`), else added as a force. `limits`: the MJCF's
    joint ranges as stiff one-sided springs (`JointLimits`), always taken implicitly. When a
    step solves implicitly, the friction's slope is taken at the step's end as well.

    `tree` (`TreePrior`): the known kinematic tree's rigid body with learned inertias
    (`RigidBodyTree`) instead of the networks' M, V and friction; with its `residual` the
    networks' mechanics are a residual Lagrangian beside it (`TreeDynamics`: M = M_tree +
    M_res, V = V_tree + V_res, the friction added), started near zero by the structure's
    ``start_level``. ``model=tree`` is a DeLaN with a tree and no residual.

    How it steps and learns is `stepping` (`Stepping`). Losses (`stepping.loss`): 'forward'
    compares the integrated next state with the data, per DoF normalised by the std of the
    one-step change; 'inverse' compares the predicted torque B a with DeLaN's inverse
    dynamics at the finite-difference acceleration (or the batch's `qdd` when present),
    normalised by the per-DoF torque std; 'both' adds them.

    A DoF without actuator has tau = 0 in every sample; its torque error is normalised by
    `unactuated_torque_scale` times the largest actuated std (a std floor would give it 10^4
    times the weight and pull M towards 0, see docs/benchmarks.md, suite identify).

    Safety at extreme inputs: `fit_normalization` also standardises the plain position
    features (bounded at +-5 std, see `QFeatures`) and sets `velocity_limit` to
    `velocity_margin` times the largest |qd| in the data per DoF; `step` evaluates the
    dynamics at velocities clamped to it and clamps the velocity it returns, so any finite
    state and action give a finite next state.

    With ``structure.yaw_invariant`` the residual force sees body-frame velocities and acts
    in that frame, and the root's linear velocity is clamped in its own frame: turning a
    state about the vertical turns the predicted accelerations with it, exactly.

    The model is plain maths: its training losses and its planning step are compiled where
    they are called (`mbrl_delan.accelerate`).
    """

    deterministic = True
    fit_kernel = "transition_losses"  # what `mbrl_delan.accelerate.compile_fit` compiles

    def __init__(
        self,
        layout: JointLayout,
        actuation: Tensor,
        control_dt: float,
        structure: Structure | None = None,
        stepping: Stepping | None = None,
        contact: ContactModel | None = None,
        limits: JointLimits | None = None,
        tree: TreePrior | None = None,
    ) -> None:
        super().__init__()
        if control_dt <= 0:
            raise ValueError(f"need control_dt > 0, got {control_dt}")
        self.structure = structure = structure or Structure()
        self.stepping = stepping = stepping or Stepping()
        self.unactuated_torque_scale = stepping.unactuated_torque_scale
        self.velocity_margin = stepping.velocity_margin
        self.layout, self.control_dt = layout, control_dt
        self.integrator, self.substeps = stepping.integrator, stepping.substeps
        self.loss_kind = stepping.loss
        self.dynamics, self.residual = structure.build(layout, actuation)
        if tree is not None:  # the known tree's rigid body, DeLaN's mechanics a residual
            residual = self.dynamics if tree.residual else None
            self.dynamics = TreeDynamics(tree.tree, self.dynamics.actuation, residual)
        self.residual_penalty = 0.0 if tree is None else tree.penalty
        self.contact, self.limits = contact, limits
        n = layout.nv
        for name in ("q_scale", "qd_scale", "tau_scale"):
            self.register_buffer(name, torch.ones(n))
        self.register_buffer("velocity_limit", torch.full((n,), float(stepping.max_velocity)))
        # true once `load_mechanics` gave M, V and the friction (with their units and feature
        # statistics): `fit_normalization` then leaves them as they are
        self.register_buffer("mechanics_loaded", torch.zeros((), dtype=torch.bool))

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        return self.dynamics.terms(q, qd)

    @torch.no_grad()
    def rigid_body(self, q: Tensor) -> RigidBody:
        """M(q), dV/dq (gravity and springs; the tree's g + k (q - q_spring)) and B."""
        terms = self.dynamics.terms(q, torch.zeros(*q.shape[:-1], self.layout.nv).to(q))
        return RigidBody(terms.mass_matrix, terms.gravity, self.dynamics.actuation)

    def joint_stiffness(self, q: Tensor) -> Tensor | None:
        """On a tree (`TreeDynamics`): its springs plus the residual potential's slope
        d g_res,j / d q_j (central differences of 1e-3 rad on the DoF's coordinate; hinges
        and slides), the median over q (S, nq); None without a tree."""
        if not isinstance(self.dynamics, TreeDynamics):
            return None
        return self.dynamics.joint_stiffness(q)

    def acceleration(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """Forward dynamics under controls: (..., nq), (..., nv), (..., nu) -> (..., nv)."""
        return self.dynamics.forward_dynamics(q, qd, self.applied_force(q, qd, action))

    def applied_force(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """B a, plus the contact and residual forces when the model has them. (..., nv)"""
        return self._with_learned_forces(self.dynamics.generalized_force(action), q, qd, action)

    def _with_learned_forces(
        self, tau: Tensor, q: Tensor, qd: Tensor, action: Tensor, contact: bool = True
    ) -> Tensor:
        """tau + the contact force (with `contact`) + r(q, qd, a) in torque units, those the
        model has. (..., nv)"""
        if self.contact is not None and contact:
            tau = tau + self.contact(q, qd)
        if self.residual is None:
            return tau
        qd_unit = self.velocity_limit / self.velocity_margin  # the largest |qd| in the data
        if not self.structure.yaw_invariant:
            return tau + self.tau_scale * self.residual(q, qd, action, qd_unit)
        R = rotation_matrix(q[..., 3:7])  # in the root's frame, turned back to the world's
        force = self.tau_scale * self.residual(q, to_root_frame(R, qd), action, qd_unit)
        return tau + from_root_frame(R, force)

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        """One control step: (..., nq), (..., nv), (..., nu) -> State((..., nq), (..., nv))."""
        tau = self.dynamics.generalized_force(action)  # B a: once per step, not per stage
        implicit_contact = self.contact is not None and self.contact.implicit
        h = self.control_dt / self.substeps

        def accel(q_: Tensor, qd_: Tensor) -> Tensor:
            qd_ = self._clamp_velocity(q_, qd_)
            force = self._with_learned_forces(tau, q_, qd_, action, contact=not implicit_contact)
            frames = self._shared_frames(q_)
            parts = self._implicit_parts(q_, qd_, h, frames)
            if not parts:
                return self.dynamics.forward_dynamics(q_, qd_, force)
            shared = {} if frames is None else {"frames": frames}
            mass_matrix, bias = self.dynamics.mass_and_bias(q_, qd_, damping_dt=h, **shared)
            return implicit_acceleration(parts, qd_, h, mass_matrix, force - bias)

        # positions move with clamped velocities: a huge learned acceleration cannot throw
        # the body further than the data's speeds allow
        return integrate(
            self.layout, accel, q, qd, self.control_dt, self.integrator, self.substeps,
            limit=self._clamp_velocity,
        )  # fmt: skip

    def _shared_frames(self, q: Tensor) -> Frames | None:
        """The tree's frames at q, computed once for its rigid body and the contacts (the
        same kinematic tree), where the model has both; else None."""
        if self.contact is None or not isinstance(self.dynamics, TreeDynamics):
            return None
        return self.dynamics.tree.fk.dof_axes(q)

    def _implicit_parts(
        self, q: Tensor, qd: Tensor, dt: float, frames: Frames | None = None
    ) -> list[ImplicitTerms]:
        """What a step of `dt` takes implicitly: the contacts (when implicit), the limits."""
        parts = []
        if self.contact is not None and self.contact.implicit:
            parts.append(self.contact.implicit_terms(q, qd, dt, frames))
        if self.limits is not None:
            parts.append(self.limits.implicit_terms(q, qd, dt))
        return parts

    def _clamp_velocity(self, q: Tensor, qd: Tensor) -> Tensor:
        """qd within +-`velocity_limit` per DoF; with `yaw_invariant` the root's linear
        velocity is clamped in its own frame, so the clamp turns with the body too."""
        limit = self.velocity_limit
        if not self.structure.yaw_invariant:
            return torch.clamp(qd, -limit, limit)
        R = rotation_matrix(q[..., 3:7])
        return from_root_frame(R, torch.clamp(to_root_frame(R, qd), -limit, limit))

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """Loss scales, feature statistics and the velocity limit from training data.

        Inverse-dynamics data without ("next", ...) states set everything but the
        next-state scales (used by the forward loss only)."""
        q, qd = data[keys.Q], data[keys.QD]
        tau = self.dynamics.generalized_force(data[keys.ACTION].to(self.q_scale.dtype))
        self.tau_scale.copy_(self._torque_scale(tau))
        if keys.NEXT_Q in data.keys(include_nested=True):
            q_next, qd_next = data[keys.NEXT_Q], data[keys.NEXT_QD]
            self.q_scale.copy_(_scale(differentiate_pos(self.layout, q, q_next, 1.0)))
            self.qd_scale.copy_(_scale(qd_next - qd))
            q, qd = torch.cat([q, q_next]), torch.cat([qd, qd_next])
        if not bool(self.mechanics_loaded):
            self._fit_mechanics_units(data, q, tau)
        if self.residual is not None:
            self.residual.features.standardize(q)
        speed = qd.abs().amax(dim=0).clamp_min(1e-3)
        self.velocity_limit.copy_(self.velocity_margin * speed)

    def _fit_mechanics_units(self, data: TensorDictBase, q: Tensor, tau: Tensor) -> None:
        """The Lagrangian part's units and feature statistics from the data (q: every state)."""
        if self.structure.inertia_scaling:
            self._fit_inertia_scale(data, tau)
        field = self.dynamics.field
        if field is None:  # a tree without a residual Lagrangian: nothing learned has units
            return
        field.features.standardize(q)
        if isinstance(field, LagrangianNetwork):
            field.start_height_weight(tau, self.structure.root_weight)

    @torch.no_grad()
    def load_mechanics(self, state: Mapping[str, Tensor]) -> None:
        """Take M, V and the friction from another DeLaN of the same structure and system.

        `state`: that DeLaN's `state_dict()` (for example the mechanics of an inverse-dynamics
        fit on motion capture, `models.inverse.DeLaNInverse.delan`). Its ``dynamics.*``
        entries are copied: the networks of M and V, their units and feature statistics, the
        friction. The actuation B stays this model's (the other may map a different action,
        such as every generalized force); the residual force and the loss scales stay too.
        Afterwards `fit_normalization` keeps the mechanics' units and statistics, so
        refitting starts from the loaded M(q), V(q). A missing entry or one of another shape
        (another width, depth, system or structure option) raises ValueError naming it.
        """
        own = {k: v for k, v in self.state_dict().items() if _is_mechanics(k)}
        state = dict(state) | {  # mechanics saved before the springs had units: the old ones
            k: torch.full_like(v, SPRING_UNITS[k.rsplit(".", 1)[-1]])
            for k, v in own.items()
            if k not in state and k.rsplit(".", 1)[-1] in SPRING_UNITS
        }
        missing = sorted(k for k in own if k not in state)
        wrong = sorted(
            f"{k} {tuple(state[k].shape)} (this model: {tuple(own[k].shape)})"
            for k in own
            if k in state and state[k].shape != own[k].shape
        )
        extra = sorted(k for k in state if _is_mechanics(k) and k not in own)
        if missing or wrong or extra:
            raise ValueError(
                "the given mechanics do not fit this DeLaN: "
                + "; ".join(
                    f"{label}: {', '.join(keys_)}"
                    for label, keys_ in (
                        ("missing", missing),
                        ("other shape", wrong),
                        ("not in this model", extra),
                    )
                    if keys_
                )
            )
        for k, v in own.items():
            v.copy_(state[k].to(v))
        self.mechanics_loaded.fill_(True)

    def _fit_inertia_scale(self, data: TensorDictBase, tau: Tensor) -> None:
        """Units from the data, all positive constants (the structure is kept):

        - M = D L~ L~^T D with D_i^2 = std(tau_i) / std(qdd_i), an inertia per DoF (qdd from
          the data's `qdd`, else finite differences);
        - V in units of the largest torque std;
        - viscous friction in std(tau_i) / rms(qd_i), Coulomb friction in std(tau_i).

        A DoF whose qdd or qd does not vary (spread below `CONSTANT_RATIO` of the largest)
        but whose torque does is held still against gravity and its neighbours' motion (the
        mocap's clavicles, fingers, thumbs): its inertia unit is std(tau_i) over the moving
        DoFs' geometric-mean qdd std (the fingers: ~0.003, not the body's ~0.6). A DoF whose
        torque does not vary either (unactuated) gets the geometric mean of the others' units,
        as do its friction units. Starts M near the data's inertia scale, which matters when
        it spans decades (a humanoid: 40 kg root, 0.02 kg m^2 wrists).
        """
        qdd = data.get(keys.QDD, None)
        if qdd is None:
            qdd = (data[keys.NEXT_QD] - data[keys.QD]) / self.control_dt
        qd = data[keys.QD].to(tau.dtype)
        tau_std, qdd_std = tau.std(dim=0), qdd.to(tau.dtype).std(dim=0)
        qd_rms = qd.pow(2).mean(dim=0).sqrt()
        known = _varies(tau_std) & _varies(qdd_std) & _varies(qd.std(dim=0))
        field = self.dynamics.field
        if not known.any() or field is None:
            return
        inertia = _fill_geometric(tau_std / qdd_std, known)
        held = _varies(tau_std) & ~known  # torque without motion
        typical_qdd = qdd_std[known].log().mean().exp()
        inertia = torch.where(held, tau_std / typical_qdd, inertia)
        root = self.structure.root_inertia
        if root is not None:  # known: the free root's own units
            inertia[:6] = torch.tensor(root, dtype=inertia.dtype, device=inertia.device)
        field.row_scale.copy_(inertia.sqrt())
        field.energy_scale.fill_(float(tau_std.max()))
        if isinstance(field, LagrangianNetwork) and field.still_potential:
            still_tau = tau_std.index_select(0, field.features.plain_v)
            field.still_scale.copy_(still_tau.clamp_min(CONSTANT_RATIO * float(tau_std.max())))
        if isinstance(field, LagrangianNetwork):
            field.set_spring_units(data[keys.Q], tau_std)
        dissipation = self.dynamics.dissipation
        if dissipation is not None:
            dissipation.viscous_scale.copy_(_fill_geometric(tau_std / qd_rms, known))
            dissipation.coulomb_scale.copy_(_fill_geometric(tau_std, _varies(tau_std)))

    def _torque_scale(self, tau: Tensor) -> Tensor:
        """Per-DoF torque std; unactuated DoFs get `unactuated_torque_scale` x the largest."""
        scale = _scale(tau)
        unactuated = self.dynamics.actuation.abs().sum(dim=-1) == 0
        if unactuated.any() and not unactuated.all():
            scale[unactuated] = self.unactuated_torque_scale * scale[~unactuated].max()
        return scale

    @property
    def trains_on_windows(self) -> bool:  # type: ignore[override]
        return self.loss_kind != "inverse"

    def loss(self, batch: TensorDictBase) -> LossOutput:
        """Per-transition loss on (B,); on windows (B, K), the forward term is the mean over
        a K-step rollout from each window's first state (`rollout_mse`) and the inverse term
        (loss 'both') is taken on each window's first transition."""
        windows = batch.batch_dims == 2
        terms: dict[str, Tensor] = {}
        if windows:
            if not self.trains_on_windows:
                raise ValueError("windows of transitions need loss 'forward' or 'both'")
            rollout = self._rollout_mse(batch)  # (K,)
            terms = {"rollout_mse": rollout.mean(), "forward_mse": rollout[0]}
            batch = batch[:, 0]  # the inverse term below: first transitions only
        inputs = {name: batch.get(key, None) for name, key in LOSS_INPUTS.items()}
        terms |= self.transition_losses(**inputs, forward=not windows)
        forward_term = "rollout_mse" if windows else "forward_mse"
        total = sum(terms[k] for k in (forward_term, "inverse_mse") if k in terms)
        if "residual_mse" in terms:
            total = total + self.residual_penalty * terms["residual_mse"]
        metrics = {name: float(value.detach()) for name, value in terms.items()}
        metrics["loss"] = float(total.detach())
        return LossOutput(loss=total, metrics=metrics)

    def transition_losses(
        self,
        q: Tensor,
        qd: Tensor,
        action: Tensor,
        qdd: Tensor | None,
        next_q: Tensor | None,
        next_qd: Tensor | None,
        forward: bool = True,
    ) -> dict[str, Tensor]:
        """The loss terms of transitions (B,) as scalars: `forward_mse` (when `forward` and
        the loss has it), `inverse_mse`, at `qdd` or else the finite difference, and with a
        `residual_penalty`, `residual_mse`: the tree residual's share of the inverse
        dynamics, ||(M_res qdd + c_res + g_res + d_res) / tau_scale||^2 per DoF, which the
        loss adds times the penalty so that the residual takes only what the tree cannot;
        the residual's quadratic spring potential (``structure.spring_potential``: springs no
        rigid body holds) is left out of g_res, so the penalty does not weaken the springs."""
        terms = {}
        if forward and self.loss_kind in ("forward", "both"):
            next_q, next_qd = _needed(next_q, keys.NEXT_Q), _needed(next_qd, keys.NEXT_QD)
            terms["forward_mse"] = self._state_mse(self.step(q, qd, action), next_q, next_qd)
        if qdd is None and (self.residual_penalty > 0 or self.loss_kind != "forward"):
            qdd = (_needed(next_qd, keys.NEXT_QD) - qd) / self.control_dt
        if self.residual_penalty > 0:
            lagrangian = self.dynamics.residual
            residual = lagrangian.inverse_dynamics(q, qd, qdd)  # (B, nv)
            if isinstance(lagrangian.field, LagrangianNetwork):
                residual = residual - lagrangian.field.spring_force(q)
            terms["residual_mse"] = (residual / self.tau_scale).pow(2).mean()
        if self.loss_kind in ("inverse", "both"):
            tau = self.applied_force(q, qd, action)
            e_tau = (self.dynamics.inverse_dynamics(q, qd, qdd) - tau) / self.tau_scale
            terms["inverse_mse"] = e_tau.pow(2).mean()
        return terms

    def _state_mse(self, pred: State, q_next: Tensor, qd_next: Tensor) -> Tensor:
        """Per-DoF normalised squared error of a predicted next state (scalar)."""
        e_q = differentiate_pos(self.layout, q_next, pred.q, 1.0) / self.q_scale
        e_qd = (pred.qd - qd_next) / self.qd_scale
        return e_q.pow(2).mean() + e_qd.pow(2).mean()

    def _rollout_mse(self, windows: TensorDictBase) -> Tensor:
        """`_state_mse` at each step of the model's rollout through windows (B, K). (K,)"""
        state = State(q=windows[keys.Q][:, 0], qd=windows[keys.QD][:, 0])
        errors = []
        for k in range(windows.shape[1]):
            state = self.step(state.q, state.qd, windows[keys.ACTION][:, k])
            errors.append(
                self._state_mse(state, windows[keys.NEXT_Q][:, k], windows[keys.NEXT_QD][:, k])
            )
        return torch.stack(errors)
