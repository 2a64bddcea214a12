"""Model fidelity on the oracle's own standing states: what a planner needs from a model.

A `FidelityReference` is built once from one oracle episode in the real env: its states
every `every`-th control step (the starts), a copy of each with perturbed joint velocities,
the actions the oracle took from each start, what the env's own physics (the MJCF as the env
steps it) makes of them, and the candidate action sequences the oracle's planner scored at
each start with their returns under the env's physics. `fidelity_metrics` then scores a
world model on it:

- ``root_velocity_error_1step`` (m/s): RMS over starts of the error of the root's horizontal
  velocity one control step ahead, on the oracle's action;
- ``head_height_error_<h>step`` (cm): RMS over starts of the head-height error after h
  open-loop steps of the oracle's actions (h in `horizons`);
- ``candidate_rank_rho``: Spearman's rho between the model's and the env physics' returns of
  the planner's candidates, the mean over the unperturbed starts (1: the model ranks the
  candidates as the env would).

The steps a planner survives when it plans in the model and acts in the env is the fourth
figure (`benchmarks/fidelity.py`; the loop's evaluation episodes).

`rigid_body_metrics` compares a model's rigid body (`WorldModel.rigid_body`: DeLaN, the tree,
the white box) with MuJoCo's at the reference's states (medians over the states):

- ``mass_matrix_error``: |M - M*|_F / |M*|_F against `mj_fullM`;
- ``total_mass_error``: |M_zz - m*| / m*, M_zz the free root's vertical translation (the
  mass the body's weight acts on), m* the MJCF's total mass;
- ``gravity_error``: |g - g*| / |g*|, g the force that holds the body at rest against gravity
  and the joints' springs (DeLaN: dV/dq), g* MuJoCo's ``qfrc_bias - qfrc_passive`` at rest;
- ``gravity_identity_residual``: |g_root - |gravity| M[root, z]| / |g_root| over the free
  root's six rows (where no spring acts): 0 for any rigid body under uniform gravity;
- ``actuation_response_error``: |M^-1 B - M*^-1 B|_F / |M*^-1 B|_F, the acceleration per unit
  of action the planner feels;
- ``spring_stiffness_error`` (where the physics' joint springs differ from the given MJCF's):
  the median over those DoFs of |k - k*| / k*;
- ``coupled_stiffness_error`` (where the physics has tendon springs, which couple joints):
  |K - K*|_F / |K*|_F on the legs' hinges (`LEG_JOINTS`), K = dg/dq the Hessian of the
  model's potential and K* MuJoCo's (central differences of `STIFFNESS_STEP`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np
import torch
from scipy.stats import spearmanr
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.models.base import WorldModel, eval_mode, model_placement
from mbrl_delan.models.inertial import dof_stiffness, rigid_body_at
from mbrl_delan.objectives.base import ObjectiveFactory, as_objective_factory
from mbrl_delan.objectives.mujoco import ENV_PHYSICS, MujocoObjectiveFactory
from mbrl_delan.systems.jacobian import central_jacobian
from mbrl_delan.systems.system import FREE, System
from mbrl_delan.tasks.humanoid import HumanoidTask

LEG_JOINTS = ("abdomen_y", "hip", "knee")  # the coupled stiffness's joints: names holding these
STIFFNESS_STEP = 1e-3  # rad: the central differences of the stiffness matrices
HORIZONS = (10, 30)  # head-height error horizons, control steps
EVERY = 10  # a start every this many control steps of the oracle's episode
VELOCITY_NOISE = 0.1  # perturbed starts: qd + this x the episode's per-DoF std x N(0, 1)


class CandidateRecorder(ObjectiveFactory):
    """An objective factory that passes through to `factory` and keeps, every `every`-th
    objective it makes (of its first `until`; None: all), the start (q0, qd0) and the first
    batch of actions (N, H, nu) the planner scores (its candidates)."""

    def __init__(self, factory: Any, every: int = EVERY, until: int | None = None) -> None:
        self.factory = as_objective_factory(factory)
        self.every, self.until = every, until
        self.calls = 0
        self.starts: list[tuple[int, Tensor, Tensor]] = []  # (plan number, q0, qd0)
        self.candidates: list[Tensor] = []

    @property
    def time_indexed(self) -> bool:
        return self.factory.time_indexed

    @property
    def planning_threads(self) -> int | None:
        return self.factory.planning_threads

    def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0) -> Callable[[Tensor], Tensor]:
        objective = self.factory(q0, qd0, step)
        number, self.calls = self.calls, self.calls + 1
        if number % self.every or (self.until is not None and number >= self.until):
            return objective
        first = True

        def recorded(actions: Tensor) -> Tensor:
            nonlocal first
            if first:
                self.starts.append((number, q0.detach().clone(), qd0.detach().clone()))
                self.candidates.append(actions.detach().to("cpu", torch.float32).clone())
                first = False
            return objective(actions)

        return recorded

    def close(self) -> None:
        self.factory.close()


@dataclass
class FidelityReference:
    """The oracle's standing states and what the env's physics makes of them (module
    docstring). S starts (the episode's, then their perturbed copies), C of them with
    candidates."""

    q: Tensor  # (S, nq) float64
    qd: Tensor  # (S, nv)
    actions: Tensor  # (S, Hmax, nu): the oracle's actions from each start
    root_velocity: Tensor  # (S, 2) the env's root x, y velocity one step ahead
    head_height: Tensor  # (S, len(horizons)) the env's head height after each horizon
    horizons: tuple[int, ...]
    candidate_starts: Tensor  # (C,) int64 rows of q, qd
    candidates: Tensor  # (C, N, H, nu) float32
    candidate_returns: Tensor  # (C, N) under the env's physics
    meta: dict[str, Any] = field(default_factory=dict)

    def state_dict(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> FidelityReference:
        return cls(**{**state, "horizons": tuple(state["horizons"])})


def build_reference(
    rollout: TensorDictBase,
    recorder: CandidateRecorder,
    system: System,
    task: HumanoidTask,
    horizons: tuple[int, ...] = HORIZONS,
    every: int = EVERY,
    seed: int = 0,
    nthread: int = 1,
) -> FidelityReference:
    """The reference of one oracle episode `rollout` (T,) whose planner's factory was
    wrapped by `recorder` (a plan every control step)."""
    from mbrl_delan.training.whitebox import MjStepper  # the white-box stepper, also the truth

    q = rollout.get(keys.Q).to(torch.float64)
    qd = rollout.get(keys.QD).to(torch.float64)
    action = rollout.get(keys.ACTION).to(torch.float64)
    longest = max(horizons)
    if q.shape[0] <= longest:
        raise ValueError(
            f"the oracle's episode has {q.shape[0]} steps: too short for {longest}-step errors"
        )
    t = torch.arange(0, q.shape[0] - longest, every)  # starts with `longest` actions after
    gen = torch.Generator().manual_seed(seed)
    noise = VELOCITY_NOISE * qd.std(0) * torch.randn((t.numel(), system.nv), generator=gen,
                                                      dtype=torch.float64)  # fmt: skip
    q0 = torch.cat([q[t], q[t]])
    qd0 = torch.cat([qd[t], qd[t] + noise])
    acts = action[t[:, None] + torch.arange(longest)].repeat(2, 1, 1)  # (S, Hmax, nu)
    model = system.mj_model()
    stepper = MjStepper(model, system.frame_skip, nthread)
    try:
        ctrl = acts.clamp(system.ctrl_low, system.ctrl_high).numpy()
        q_true, qd_true = stepper(model, q0.numpy(), qd0.numpy(), ctrl)
    finally:
        stepper.close()
    q_true, qd_true = torch.from_numpy(q_true), torch.from_numpy(qd_true)
    head = torch.stack([task.head_height(q_true[:, h - 1]) for h in horizons], -1)
    rows, cands, returns = _candidates(recorder, t, system, task, nthread)
    return FidelityReference(
        q=q0, qd=qd0, actions=acts, root_velocity=qd_true[:, 0, 0:2], head_height=head,
        horizons=tuple(horizons), candidate_starts=rows, candidates=cands,
        candidate_returns=returns, meta={"episode_steps": int(q.shape[0]), "every": every},
    )  # fmt: skip


def _candidates(
    recorder: CandidateRecorder, t: Tensor, system: System, task: HumanoidTask, nthread: int
) -> tuple[Tensor, Tensor, Tensor]:
    """The recorded candidates at the starts `t` (plan number = control step) and their
    returns under the env's own physics. -> rows (C,), candidates (C, N, H, nu), (C, N)"""
    kept = {number: i for i, (number, _, _) in enumerate(recorder.starts)}
    rows = [row for row, step in enumerate(t.tolist()) if step in kept]
    if not rows:
        raise ValueError("no candidates were recorded at the reference's starts")
    env = MujocoObjectiveFactory(system, task, nthread, physics=ENV_PHYSICS)
    cands, returns = [], []
    try:
        for row in rows:
            _, q0, qd0 = recorder.starts[kept[int(t[row])]]
            actions = recorder.candidates[kept[int(t[row])]]
            cands.append(actions)
            returns.append(env(q0, qd0)(actions).to(torch.float64))
    finally:
        env.close()
    return torch.tensor(rows), torch.stack(cands), torch.stack(returns)


@torch.no_grad()
def fidelity_metrics(
    model: WorldModel, objective_factory: Any, reference: FidelityReference, task: HumanoidTask
) -> dict[str, float]:
    """The module docstring's figures of `model` (its `step`) and of the objective the planner
    plans on with it (`objective_factory`, (q0, qd0) -> objective over (N, H, nu))."""
    place = model_placement(model)
    on = lambda x: x.to(place.device, place.dtype)  # noqa: E731
    q, qd = on(reference.q), on(reference.qd)
    head = []
    with eval_mode(model):
        for h in range(max(reference.horizons)):
            state = model.step(q, qd, on(reference.actions[:, h]))
            q, qd = state.q, state.qd
            if h == 0:
                root = qd[:, 0:2].to("cpu", torch.float64)
            if h + 1 in reference.horizons:
                head.append(task.head_height(q.to("cpu", torch.float64)))
    out = {"root_velocity_error_1step": _rms(root - reference.root_velocity)}
    for k, h in enumerate(reference.horizons):
        out[f"head_height_error_{h}step"] = 100 * _rms(head[k] - reference.head_height[:, k])
    out["candidate_rank_rho"] = candidate_rank_rho(objective_factory, reference)
    return out


def candidate_rank_rho(objective_factory: Any, reference: FidelityReference) -> float:
    """Mean Spearman rho of the objective's returns of the recorded candidates against the
    env physics' returns (a start whose returns are all equal on either side counts 0)."""
    rhos = []
    for c, row in enumerate(reference.candidate_starts.tolist()):
        objective = objective_factory(reference.q[row], reference.qd[row])
        model_returns = objective(reference.candidates[c]).to("cpu", torch.float64)
        rho = spearmanr(model_returns.numpy(), reference.candidate_returns[c].numpy()).statistic
        rhos.append(0.0 if not math.isfinite(float(rho)) else float(rho))
    return float(np.mean(rhos))


@dataclass
class RigidBodyTruth:
    """MuJoCo's rigid body at the reference's states (`rigid_body_at`)."""

    q: Tensor  # (S, nq) float64
    mass_matrix: Tensor  # (S, nv, nv)
    potential_force: Tensor  # (S, nv)
    actuation: Tensor  # (nv, nu)
    total_mass: float
    gravity: float  # |g|, m/s^2
    stiffness: Tensor  # (nv,) each DoF's spring in the physics
    given_stiffness: Tensor  # (nv,) ... in the MJCF the models are given
    legs: Tensor | None = None  # (m, 2) the legs' (qpos, DoF) indices, where the physics
    coupled_stiffness: Tensor | None = None  # (S, m, m) K* there  ... has tendon springs

    @classmethod
    def of(cls, physics: System, q: Tensor, given: System | None = None) -> RigidBodyTruth:
        """The env's physics at configurations q (S, nq); `given`: the system the models
        are given, where it differs (its springs)."""
        model = physics.mj_model()
        mass, force = rigid_body_at(model, q.to(torch.float64).numpy())
        stiffness = torch.from_numpy(dof_stiffness(model))
        given_stiffness = (
            stiffness if given is None else torch.from_numpy(dof_stiffness(given.mj_model()))
        )
        legs, coupled = None, None
        if bool((np.asarray(model.tendon_stiffness).reshape(model.ntendon, -1)[:, 0] > 0).any()):
            legs = torch.as_tensor(leg_joints(model))
            coupled = torch.from_numpy(mujoco_stiffness(model, q.to(torch.float64).numpy(),
                                                        legs.tolist()))  # fmt: skip
        return cls(q.to(torch.float64), torch.from_numpy(mass), torch.from_numpy(force),
                   physics.actuation.to(torch.float64), float(model.body_mass.sum()),
                   float(np.linalg.norm(model.opt.gravity)), stiffness,
                   given_stiffness, legs, coupled)  # fmt: skip


def leg_joints(model: mujoco.MjModel) -> list[tuple[int, int]]:
    """(qpos index, DoF) of each hinge whose name holds one of `LEG_JOINTS`."""
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    return [(int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])) for j in range(model.njnt)
            if model.jnt_type[j] == hinge
            and any(part in (model.joint(j).name or "") for part in LEG_JOINTS)]  # fmt: skip


def mujoco_stiffness(model: mujoco.MjModel, q: np.ndarray, joints: list[list[int]]
                     ) -> np.ndarray:  # fmt: skip
    """K* = d(qfrc_bias - qfrc_passive at rest)/dq among hinges `joints` ((qpos, DoF)
    pairs) at q (S, nq). (S, m, m)"""
    dofs = [dof for _, dof in joints]
    force = lambda x: rigid_body_at(model, x)[1][:, dofs]  # noqa: E731
    return central_jacobian(force, q, [index for index, _ in joints], STIFFNESS_STEP)


@torch.no_grad()
def rigid_body_metrics(model: WorldModel, truth: RigidBodyTruth) -> dict[str, float]:
    """The module docstring's rigid-body figures of `model` ({} for a model without a rigid
    body); the total mass and the identity only for a free root (its z translation at v 2)."""
    place = model_placement(model)
    body = model.rigid_body(truth.q.to(place.device, place.dtype))
    if body is None:
        return {}
    mass = body.mass_matrix.to("cpu", torch.float64)
    force = body.potential_force.to("cpu", torch.float64)
    B = body.actuation.to("cpu", torch.float64)
    response = torch.linalg.solve(mass, B.expand(*mass.shape[:-1], B.shape[-1]))
    true_response = torch.linalg.solve(truth.mass_matrix, truth.actuation.expand_as(response))
    out = {
        "mass_matrix_error": _median_relative(mass, truth.mass_matrix),
        "gravity_error": _median_relative(force, truth.potential_force),
        "actuation_response_error": _median_relative(response, true_response),
    }
    if model.layout is not None and model.layout.types[:1] == (FREE,):
        m_zz = mass[:, 2, 2]
        out["total_mass_error"] = float(((m_zz - truth.total_mass).abs() / truth.total_mass)
                                        .median())  # fmt: skip
        root = force[:, :6]
        residual = root - truth.gravity * mass[:, :6, 2]
        out["gravity_identity_residual"] = float((residual.norm(dim=-1) / root.norm(dim=-1))
                                                 .median())  # fmt: skip
    return (
        out
        | _stiffness_figures(model, truth, place)
        | _coupled_stiffness_figures(model, truth, place)
    )


def _stiffness_figures(model: WorldModel, truth: RigidBodyTruth, place: Any) -> dict[str, float]:
    """Where the physics' springs differ from the given MJCF's (the exoskeleton) and the
    model can tell its springs from gravity: ``spring_stiffness_error``, the median over
    those DoFs of |k - k*| / k*, and ``spring_stiffness_ratio``, the median of k / k*."""
    changed = (truth.stiffness - truth.given_stiffness).abs() > 1e-9 * (1 + truth.stiffness)
    if not bool(changed.any()):
        return {}
    learned = model.joint_stiffness(truth.q.to(place.device, place.dtype))
    if learned is None:
        return {}
    learned = learned.to("cpu", torch.float64)
    error = (learned - truth.stiffness).abs() / truth.stiffness
    ratio = learned / truth.stiffness
    return {"spring_stiffness_error": float(error[changed].median()),
            "spring_stiffness_ratio": float(ratio[changed].median())}  # fmt: skip


def _coupled_stiffness_figures(model: WorldModel, truth: RigidBodyTruth, place: Any
                               ) -> dict[str, float]:  # fmt: skip
    """``coupled_stiffness_error`` (module docstring) where the physics has tendon springs."""
    if truth.legs is None or truth.coupled_stiffness is None:
        return {}
    q, dofs = truth.q.to(place.device, place.dtype), truth.legs[:, 1].tolist()
    force = lambda x: model.rigid_body(x).potential_force[:, dofs]  # noqa: E731
    learned = central_jacobian(force, q, truth.legs[:, 0].tolist(), STIFFNESS_STEP)
    learned = learned.to("cpu", torch.float64)
    return {"coupled_stiffness_error": _median_relative(learned, truth.coupled_stiffness)}


def _median_relative(x: Tensor, truth: Tensor) -> float:
    """Median over the first dim of |x - truth| / |truth| (Frobenius over the rest)."""
    error = (x - truth).flatten(1).norm(dim=-1) / truth.flatten(1).norm(dim=-1)
    return float(error.median()) if bool(torch.isfinite(error).all()) else math.inf


def _rms(x: Tensor) -> float:
    """RMS over rows of the row norms; non-finite predictions count as inf."""
    norms = x.reshape(x.shape[0], -1).norm(dim=-1)
    return float(norms.square().mean().sqrt()) if bool(torch.isfinite(norms).all()) else math.inf
