"""The white-box world model: the env's own MJCF, its parameters identified from data.

`WhiteBoxModel` keeps the robot's structure as MuJoCo knows it (the kinematic tree, the joint
types, the collision geometry, the actuators) and identifies the numbers a user rarely knows
well with MuJoCo's system identification (`mujoco.sysid`): each body's mass (its rotational
inertia scaled with it, so every body stays physically consistent), the joints' damping and
armature, and each contact group's `solref` time constant and damping ratio and its friction.
Every parameter is a multiplier of the MJCF's own value (1: the file as it is).

It is fitted by `identify` (nonlinear least squares on open-loop windows of the replay
buffer, rolled out by `mujoco.rollout` at the env's own physics) and planned on as the
oracle is (`objective_factory`: `mujoco.rollout` at `PlanPhysics`). It is the anchor of what
known structure buys: the learned models are compared with it.

Contact groups: every geom that can touch the floor belongs to the group of its body when
that body is a leaf of the tree (the humanoid's feet and hands), else to the group ``body``.
To give each group its own constants, each such geom's contacts with the floor become an
explicit contact pair with the values MuJoCo would have mixed for them (friction and
``condim``: the larger; ``solref`` and ``solimp``: the ``solmix``-weighted mean; margins
added), the dynamic ones excluded; contacts between bodies stay as they are. At multipliers
1 the model rolls out exactly as the MJCF (`tests/test_whitebox.py`).
"""

from __future__ import annotations

import io
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout
from mujoco import sysid
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput, ModelConfig, RigidBody, WorldModel
from mbrl_delan.models.inertial import dof_stiffness, rigid_body_at
from mbrl_delan.objectives.base import ObjectiveFactory
from mbrl_delan.objectives.mujoco import (
    FULLPHYSICS,
    QPOS,
    QVEL,
    MujocoObjectiveFactory,
    PlanPhysics,
    mujoco_threads,
    state_offset,
)
from mbrl_delan.objectives.mujoco import INTEGRATORS as MJ_INTEGRATORS
from mbrl_delan.registry import register_model
from mbrl_delan.rules import rule
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import State, System
from mbrl_delan.tasks.base import Task
from mbrl_delan.training.fit import FitReport, window_starts

log = logging.getLogger(__name__)

BODY_GROUP = "body"  # the contact group of geoms on bodies that are not leaves of the tree
# bounds of each kind of multiplier (1: the MJCF's value)
BOUNDS = {
    "mass": (0.2, 5.0),
    "damping": (0.1, 10.0),
    "armature": (0.1, 10.0),
    "timeconst": (0.2, 20.0),
    "dampratio": (0.2, 5.0),
    "friction": (0.05, 5.0),
}
# the documented wrong start (`WhiteBoxStart.documented`): what a user who took the robot's
# masses from a catalogue and MuJoCo's default contacts might begin with
WRONG_MASS_SPREAD = 0.5  # each body's mass x U(1 - 0.5, 1 + 0.5), seeded
WRONG_START = {"damping": 2.0, "armature": 0.5, "timeconst": 10.0, "dampratio": 1.0,
               "friction": 0.5}  # fmt: skip
WRONG_START_SEED = 0


@dataclass(frozen=True)
class IdentifyConfig:
    """How `WhiteBoxModel.identify` fits its parameters.

    window: control steps of each open-loop window (the model is rolled out from the
        window's first state on its actions and scored at each step).
    windows: windows drawn from the data per identification (all when fewer).
    iterations: least-squares (Levenberg-Marquardt) iterations per identification.
    fd_step: finite-difference step of the multipliers for the Jacobian.
    """

    window: int = 4
    windows: int = 256
    iterations: int = 10
    fd_step: float = 1e-4

    def __post_init__(self) -> None:
        if min(self.window, self.windows, self.iterations) < 1 or not self.fd_step > 0:
            raise ValueError(
                "window, windows and iterations must be >= 1 and fd_step > 0, got "
                f"{self.window}, {self.windows}, {self.iterations}, {self.fd_step}"
            )


@dataclass(frozen=True)
class Multiplier:
    """One identified number: `kind` (a key of `BOUNDS`) of `target` (a body, a contact
    group, or ``joints``)."""

    kind: str
    target: str

    @property
    def name(self) -> str:
        return f"{self.kind}:{self.target}"


def collision_geoms(model: mujoco.MjModel) -> tuple[int, list[int]]:
    """The floor plane (the highest plane geom) and the geoms that can touch it."""
    planes = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    if not planes:
        raise ValueError("a white-box contact model needs a floor: the MJCF has no plane geom")
    floor = max(planes, key=lambda g: model.geom_pos[g, 2])
    touching = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] != 0
        and (
            model.geom_contype[g] & model.geom_conaffinity[floor]
            or model.geom_contype[floor] & model.geom_conaffinity[g]
        )
    ]
    return floor, touching


def has_floor(model: mujoco.MjModel) -> bool:
    return bool((model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE).any())


def contact_groups(model: mujoco.MjModel) -> dict[str, list[int]]:
    """Group name -> the floor-touching geoms in it: a leaf body's own name, else `BODY_GROUP`
    (none without a floor)."""
    if not has_floor(model):
        return {}
    _, touching = collision_geoms(model)
    parents = set(int(p) for p in model.body_parentid[1:])
    groups: dict[str, list[int]] = {}
    for g in touching:
        body = int(model.geom_bodyid[g])
        name = model.body(body).name if body not in parents else BODY_GROUP
        groups.setdefault(name or f"body{body}", []).append(g)
    return groups


class WhiteBoxSpec:
    """An MJCF prepared for identification and the multipliers that edit it.

    The base spec has explicit inertials (the compiled ones, for models whose inertia comes
    from their geoms) and its floor contacts given to the touching geoms (module docstring).
    `build(theta)` returns the MjModel at multipliers theta (M,) through the `sysid`
    parameters' modifiers.
    """

    def __init__(self, spec: mujoco.MjSpec) -> None:
        self.base = spec.copy()
        model = self.base.compile()
        self.bodies = [model.body(b).name for b in range(1, model.nbody) if model.body_mass[b] > 0]
        _explicit_inertials(self.base, model)
        pairs = (
            dict(zip(collision_geoms(model)[1], _own_floor_contacts(self.base, model), strict=True))
            if has_floor(model)
            else {}
        )
        # contact group -> the names of its floor contact pairs
        self.groups = {
            name: [pairs[g] for g in geoms] for name, geoms in contact_groups(model).items()
        }
        self.multipliers = self._multipliers(model)
        self.params = sysid.ParameterDict()
        for m in self.multipliers:
            low, high = BOUNDS[m.kind]
            self.params.add(sysid.Parameter(m.name, 1.0, low, high, modifier=self._modifier(m)))

    def _multipliers(self, model: mujoco.MjModel) -> list[Multiplier]:
        out = [Multiplier("mass", body) for body in self.bodies]
        scalar = model.jnt_type >= int(mujoco.mjtJoint.mjJNT_SLIDE)  # hinges and slides
        dofs = model.jnt_dofadr[scalar]
        for kind in ("damping", "armature"):
            if bool(getattr(model, f"dof_{kind}")[dofs].any()):
                out.append(Multiplier(kind, "joints"))
        for group in self.groups:
            out += [Multiplier(kind, group) for kind in ("timeconst", "dampratio", "friction")]
        return out

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.multipliers]

    def _modifier(self, m: Multiplier) -> Callable[[mujoco.MjSpec, sysid.Parameter], None]:
        """The `sysid` modifier that writes multiplier `m` into a copy of the base spec."""
        if m.kind == "mass":
            return _mass_modifier(self.base, m.target)
        if m.kind in ("damping", "armature"):
            return _joint_modifier(self.base, m.kind)
        return _contact_modifier(self.base, m.kind, self.groups[m.target])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.params.get_bounds()

    def build(self, theta: np.ndarray) -> mujoco.MjModel:
        """The MjModel at multipliers theta (M,), built on a copy of the base spec."""
        params = self.params.copy()
        params.update_from_vector(np.asarray(theta, dtype=np.float64).reshape(-1))
        return sysid.apply_param_modifiers(params, self.base.copy())

    def documented_start(self) -> np.ndarray:
        """The documented wrong model (`WRONG_START`, masses x U(0.5, 1.5) with seed
        `WRONG_START_SEED`) as multipliers (M,), inside the bounds."""
        rng = np.random.default_rng(WRONG_START_SEED)
        theta = np.ones(len(self.multipliers))
        for i, m in enumerate(self.multipliers):
            if m.kind == "mass":
                theta[i] = rng.uniform(1 - WRONG_MASS_SPREAD, 1 + WRONG_MASS_SPREAD)
            else:
                theta[i] = WRONG_START[m.kind]
        low, high = self.bounds()
        return np.clip(theta, low, high)


Modifier = Callable[[mujoco.MjSpec, sysid.Parameter], None]


def _mass_modifier(base: mujoco.MjSpec, body: str) -> Modifier:
    """A body's mass and rotational inertia, both x the parameter (still consistent)."""
    mass, inertia = float(base.body(body).mass), np.array(base.body(body).inertia)

    def scale_body(spec: mujoco.MjSpec, p: sysid.Parameter) -> None:
        target = spec.body(body)
        target.mass, target.inertia = mass * float(p.value[0]), inertia * float(p.value[0])

    return scale_body


def _joint_modifier(base: mujoco.MjSpec, kind: str) -> Modifier:
    """Every hinge's and slide's `kind` (damping, armature) x the parameter."""
    nominal = [np.array(getattr(j, kind)) for j in _scalar_joints(base)]

    def scale_joints(spec: mujoco.MjSpec, p: sysid.Parameter) -> None:
        for joint, value in zip(_scalar_joints(spec), nominal, strict=True):
            setattr(joint, kind, value * float(p.value[0]))

    return scale_joints


def _contact_modifier(base: mujoco.MjSpec, kind: str, pairs: list[str]) -> Modifier:
    """The `kind` (timeconst, dampratio, friction) of a group's floor pairs x the parameter;
    the pairs' other values kept."""
    attr, cols = {"timeconst": ("solref", [0]), "dampratio": ("solref", [1]),
                  "friction": ("friction", [0, 1])}[kind]  # fmt: skip
    nominal = [np.array(getattr(base.pair(name), attr)) for name in pairs]

    def scale_contacts(spec: mujoco.MjSpec, p: sysid.Parameter) -> None:
        for name, value in zip(pairs, nominal, strict=True):
            values = np.array(getattr(spec.pair(name), attr))
            values[cols] = value[cols] * float(p.value[0])
            setattr(spec.pair(name), attr, values)

    return scale_contacts


def _scalar_joints(spec: mujoco.MjSpec) -> list[Any]:
    scalar = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
    return [j for j in spec.joints if j.type in scalar]


def _explicit_inertials(spec: mujoco.MjSpec, model: mujoco.MjModel) -> None:
    """Every body's inertial as the compiled model has it (so masses can be scaled)."""
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO
    for b in range(1, model.nbody):
        body = spec.body(model.body(b).name)
        body.explicitinertial = True
        body.fullinertia = np.full(6, np.nan)
        body.mass = float(model.body_mass[b])
        body.inertia = model.body_inertia[b].copy()
        body.ipos = model.body_ipos[b].copy()
        body.iquat = model.body_iquat[b].copy()


def _own_floor_contacts(spec: mujoco.MjSpec, model: mujoco.MjModel) -> list[str]:
    """Each floor-touching geom's contacts with the floor as an explicit contact pair with the
    values MuJoCo mixes for that pair (the floor's and the body's dynamic contacts excluded),
    so a group's multipliers act on its floor contacts alone and contacts between bodies stay
    as they were. Returns the pairs' names, in geom order."""
    floor, touching = collision_geoms(model)
    floor_name = _name_geom(spec, model, floor)
    for body in sorted({int(model.geom_bodyid[g]) for g in touching}):
        spec.add_exclude(bodyname1=model.body(0).name, bodyname2=model.body(body).name)
    names = []
    for g in touching:
        w1, w2 = model.geom_solmix[g], model.geom_solmix[floor]
        mix = 0.5 if w1 + w2 < mujoco.mjMINVAL else w1 / (w1 + w2)
        friction = np.maximum(model.geom_friction[g], model.geom_friction[floor])
        pair = spec.add_pair(
            name=f"floor_{_name_geom(spec, model, g)}",
            geomname1=floor_name,
            geomname2=_name_geom(spec, model, g),
            condim=int(max(model.geom_condim[g], model.geom_condim[floor])),
            friction=friction[[0, 0, 1, 2, 2]],
            solref=mix * model.geom_solref[g] + (1 - mix) * model.geom_solref[floor],
            solimp=mix * model.geom_solimp[g] + (1 - mix) * model.geom_solimp[floor],
            margin=float(model.geom_margin[g] + model.geom_margin[floor]),  # MuJoCo adds them
            gap=float(model.geom_gap[g] + model.geom_gap[floor]),
        )
        names.append(pair.name)
    return names


def _name_geom(spec: mujoco.MjSpec, model: mujoco.MjModel, g: int) -> str:
    """Geom g's name, giving it one when it has none."""
    geom = spec.geoms[g]
    if not geom.name:
        geom.name = f"geom{g}"
    return geom.name


class MjStepper:
    """Control steps of one or more MjModels from (q, qd) states with `mujoco.rollout`.

    Each control is held for `substeps` physics steps; the states start with no warm start
    and no actuator activation (what a replay buffer's (q, qd) holds)."""

    def __init__(self, model: mujoco.MjModel, substeps: int, nthread: int = 1) -> None:
        self.substeps, self.nq, self.nv = substeps, model.nq, model.nv
        self.qpos_at, self.qvel_at = state_offset(model, QPOS), state_offset(model, QVEL)
        data = mujoco.MjData(model)
        self.template = np.empty(mujoco.mj_stateSize(model, FULLPHYSICS))
        mujoco.mj_getState(model, data, self.template, FULLPHYSICS)
        self.nthread = nthread
        self._datas = [mujoco.MjData(model) for _ in range(nthread)]
        self._pool = mj_rollout.Rollout(nthread=nthread if nthread > 1 else 0)

    def close(self) -> None:
        self._pool.close()

    def states(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """FULLPHYSICS states (N, nstate) at q (N, nq), qd (N, nv)."""
        out = np.repeat(self.template[None], q.shape[0], axis=0)
        out[:, self.qpos_at : self.qpos_at + self.nq] = q
        out[:, self.qvel_at : self.qvel_at + self.nv] = qd
        return out

    def __call__(
        self, models: mujoco.MjModel | Sequence[mujoco.MjModel], q: np.ndarray, qd: np.ndarray,
        ctrl: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """From q (N, nq), qd (N, nv) under controls (N, T, nu): the states after each
        control step, q (N, T, nq) and qd (N, T, nv)."""
        control = np.ascontiguousarray(np.repeat(ctrl, self.substeps, axis=1))
        out = np.empty((q.shape[0], control.shape[1], self.template.size))
        self._pool.rollout(models, self._datas, self.states(q, qd), control, state=out)
        reached = out[:, self.substeps - 1 :: self.substeps]
        return (
            reached[..., self.qpos_at : self.qpos_at + self.nq],
            reached[..., self.qvel_at : self.qvel_at + self.nv],
        )


class WhiteBoxModel(WorldModel):
    """The env's MJCF with identified multipliers (module docstring).

    Args:
        system: the env's system (its MJCF, control period and physics).
        spec: the MJCF to start from (None: the system's file); a perturbed copy gives the
            fidelity suite's reference models.
        start: multipliers to start from (M,), None: 1 (the MJCF's own values);
            `WhiteBoxSpec.documented_start` gives the documented wrong model.
        physics: how the model steps when it predicts and plans (`PlanPhysics`).
        identify: the identification settings.
        nthread: MuJoCo threads of its rollouts.
    """

    deterministic = True
    identifies = True

    def __init__(
        self,
        system: System,
        spec: mujoco.MjSpec | None = None,
        start: np.ndarray | None = None,
        physics: PlanPhysics | None = None,
        identify: IdentifyConfig | None = None,
        nthread: int = 1,
    ) -> None:
        super().__init__()
        self.system, self.layout = system, system.layout
        self.white = WhiteBoxSpec(spec or mujoco.MjSpec.from_file(str(system.xml_path)))
        theta = np.ones(len(self.white.multipliers)) if start is None else np.asarray(start)
        if theta.shape != (len(self.white.multipliers),):
            raise ValueError(
                f"start must hold {len(self.white.multipliers)} multipliers, got {theta.shape}"
            )
        self.physics = physics or PlanPhysics()
        self.settings = identify or IdentifyConfig()
        self.nthread = nthread
        self.theta = theta.astype(np.float64)
        self.identifications = 0
        self._built: tuple[mujoco.MjModel, int] | None = None
        self._stepper: MjStepper | None = None

    # ------------------------------------------------------------------ the model
    def mj_model(self) -> tuple[mujoco.MjModel, int]:
        """The planning MjModel at the current multipliers and its physics steps per
        control step (built once per set of multipliers)."""
        if self._built is None:
            model = self.white.build(self.theta)
            self._built = self.physics.apply(model, self.system)
        return self._built

    def parameters_by_name(self) -> dict[str, float]:
        return dict(zip(self.white.names, self.theta.tolist(), strict=True))

    def set_multipliers(self, theta: np.ndarray) -> None:
        """Use multipliers theta (M,) from now on."""
        self._set_theta(theta)

    def _set_theta(self, theta: np.ndarray) -> None:
        self.theta = np.asarray(theta, dtype=np.float64).copy()
        self._built = None
        if self._stepper is not None:
            self._stepper.close()
            self._stepper = None

    def get_extra_state(self) -> dict[str, Any]:
        theta = torch.from_numpy(self.theta.copy())
        return {"theta": theta, "identifications": self.identifications}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self._set_theta(state["theta"].numpy())
        self.identifications = int(state["identifications"])

    def joint_stiffness(self, q: Tensor) -> Tensor:
        """The identified MJCF's springs per DoF (hinges and slides; it does not identify
        them: the MJCF's own). (nv,)"""
        model, _ = self.mj_model()
        return torch.from_numpy(dof_stiffness(model)).to(q)

    def rigid_body(self, q: Tensor) -> RigidBody:
        """M, the potential force at rest and B of the identified MJCF (`rigid_body_at`)."""
        model, _ = self.mj_model()
        flat = q.detach().to("cpu", torch.float64).reshape(-1, q.shape[-1]).numpy()
        mass, force = rigid_body_at(model, flat)
        as_q = lambda x: torch.from_numpy(x).to(q).reshape(*q.shape[:-1], *x.shape[1:])  # noqa: E731
        return RigidBody(as_q(mass), as_q(force), self.system.actuation.to(q))

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        """One control step at the planning physics: (..., nq), (..., nv), (..., nu) ->
        State((..., nq), (..., nv)) on the inputs' device and dtype."""
        model, substeps = self.mj_model()
        if self._stepper is None:
            self._stepper = MjStepper(model, substeps, self.nthread)
        lead = q.shape[:-1]
        as_np = lambda x: x.detach().to("cpu", torch.float64).reshape(-1, x.shape[-1]).numpy()  # noqa: E731
        ctrl = np.clip(as_np(action), self.system.ctrl_low.numpy(), self.system.ctrl_high.numpy())
        q1, qd1 = self._stepper(model, as_np(q), as_np(qd), ctrl[:, None])
        back = lambda x, n: torch.from_numpy(x[:, 0].copy()).to(q).reshape(*lead, n)  # noqa: E731
        return State(q=back(q1, self.system.nq), qd=back(qd1, self.system.nv))

    def loss(self, batch: TensorDictBase) -> LossOutput:
        raise TypeError("the white-box model is identified (`identify`), not trained by a loss")

    def objective_factory(self, task: Task, discount: float = 1.0) -> WhiteBoxObjectiveFactory:
        """Its planning objective: task returns of MuJoCo rollouts of this model."""
        return WhiteBoxObjectiveFactory(self, task, discount)

    # ------------------------------------------------------------------ identification
    def identify(self, data: TensorDictBase, generator: torch.Generator) -> FitReport:
        """Fit the multipliers to open-loop windows of `data` (transitions (N,), time
        ordered), starting from the current ones; returns what happened (the residual before
        and after as the 'loss')."""
        problem = WindowProblem.from_data(self, data, generator)
        try:
            start = problem.cost(self.theta)
            params = self.white.params.copy()
            params.update_from_vector(self.theta)
            fitted, _ = sysid.optimize(
                params,
                problem.sysid_residual,
                optimizer="mujoco",
                verbose=False,
                max_iters=self.settings.iterations,
                eps=self.settings.fd_step,
                output=io.StringIO(),  # the optimizer's iteration table (kept out of the log)
            )
            theta = fitted.as_vector()
            end = problem.cost(theta)
        finally:
            problem.close()
        if math.isfinite(end) and end <= start:
            self._set_theta(theta)
        self.identifications += 1
        log.info(
            "identify: %d windows of %d steps, cost %.4g -> %.4g, %s",
            problem.windows, self.settings.window, start, end,
            " ".join(f"{k}={v:.3g}" for k, v in self.parameters_by_name().items()),
        )  # fmt: skip
        return FitReport(
            train_loss=[start, end], val_loss=[end], best_epoch=0, best_val_loss=min(start, end),
            epochs_run=self.settings.iterations, n_train=problem.windows,
            metrics=self.parameters_by_name(),
        )  # fmt: skip


class WindowProblem:
    """The least-squares problem of `WhiteBoxModel.identify`: windows of K consecutive
    transitions, rolled out at the env's own physics from each window's first state on its
    actions; the residual is each reached state's error (positions in velocity space) per
    DoF over the data's one-step change, / sqrt(count), so the cost is a mean square."""

    def __init__(
        self, model: WhiteBoxModel, q0: np.ndarray, qd0: np.ndarray, ctrl: np.ndarray,
        q_next: Tensor, qd_next: Tensor, q_scale: Tensor, qd_scale: Tensor,
    ) -> None:  # fmt: skip
        self.model, self.white = model, model.white
        self.q0, self.qd0, self.ctrl = q0, qd0, ctrl  # (W, nq), (W, nv), (W, K, nu)
        self.q_next, self.qd_next = q_next, qd_next  # (W, K, nq), (W, K, nv)
        self.q_scale, self.qd_scale = q_scale, qd_scale  # (nv,)
        env_model = self.white.build(np.ones(len(self.white.multipliers)))
        self.stepper = MjStepper(env_model, model.system.frame_skip, model.nthread)

    @property
    def windows(self) -> int:
        return self.q0.shape[0]

    @classmethod
    def from_data(
        cls, model: WhiteBoxModel, data: TensorDictBase, generator: torch.Generator
    ) -> WindowProblem:
        k = model.settings.window
        starts = window_starts(data, k).cpu()
        while starts.numel() == 0 and k > 1:  # episodes shorter than a window
            k -= 1
            starts = window_starts(data, k).cpu()
        if starts.numel() > model.settings.windows:
            pick = torch.randperm(starts.numel(), generator=generator)[: model.settings.windows]
            starts = starts[pick.sort().values]
        idx = starts[:, None] + torch.arange(k)  # (W, K)
        f64 = lambda key: data[key].detach().to("cpu", torch.float64)  # noqa: E731
        q, qd, action = f64(keys.Q), f64(keys.QD), f64(keys.ACTION)
        q_next, qd_next = f64(keys.NEXT_Q), f64(keys.NEXT_QD)
        system = model.system
        dq = differentiate_pos(system.layout, q, q_next, 1.0)
        ctrl = action[idx].clamp(system.ctrl_low, system.ctrl_high).numpy()
        return cls(
            model, q[starts].numpy(), qd[starts].numpy(), ctrl, q_next[idx], qd_next[idx],
            _spread(dq), _spread(qd_next - qd),
        )  # fmt: skip

    def close(self) -> None:
        self.stepper.close()

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """Residuals (R, C) of multipliers theta (M, C) (or (R,) of theta (M,))."""
        columns = theta.reshape(theta.shape[0], -1)
        models = [self.white.build(columns[:, c]) for c in range(columns.shape[1])]
        w = self.windows
        batch = [m for m in models for _ in range(w)]
        tile = lambda x: np.concatenate([x] * len(models))  # noqa: E731
        q, qd = self.stepper(batch, tile(self.q0), tile(self.qd0), tile(self.ctrl))
        q = torch.from_numpy(q).reshape(len(models), w, *q.shape[1:])
        qd = torch.from_numpy(qd).reshape(len(models), w, *qd.shape[1:])
        e_q = differentiate_pos(self.model.layout, self.q_next.expand_as(q), q, 1.0) / self.q_scale
        e_qd = (qd - self.qd_next) / self.qd_scale
        r = torch.cat([e_q, e_qd], -1).reshape(len(models), -1)
        r = torch.nan_to_num(r, nan=1e3, posinf=1e3, neginf=-1e3) / math.sqrt(r.shape[1])
        out = r.T.numpy()
        return out[:, 0] if theta.ndim == 1 else out

    def sysid_residual(self, x: np.ndarray, params: sysid.ParameterDict) -> tuple[list, list, list]:
        """`residual` in the form `sysid.optimize` calls."""
        return [self.residual(x)], [], []

    def cost(self, theta: np.ndarray) -> float:
        """The mean square error at multipliers theta (M,)."""
        return float(np.square(self.residual(np.asarray(theta, dtype=np.float64))).sum())


def _spread(x: Tensor, floor_ratio: float = 1e-2) -> Tensor:
    """Per-column std, floored at a fraction of the largest. (nv,)"""
    std = x.std(0) if x.shape[0] > 1 else x.abs().mean(0)
    return std.clamp_min(floor_ratio * float(std.max().clamp_min(1e-8)))


class WhiteBoxObjectiveFactory(ObjectiveFactory):
    """The white-box model's planning objective: an oracle objective (`MujocoObjectiveFactory`)
    on the model's MjModel, rebuilt when its multipliers change."""

    def __init__(self, model: WhiteBoxModel, task: Task, discount: float) -> None:
        self.model, self.task, self.discount = model, task, discount
        self._factory: MujocoObjectiveFactory | None = None
        self._for: mujoco.MjModel | None = None

    @property
    def time_indexed(self) -> bool:
        return self.task.time_indexed

    def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0) -> Any:
        mj_model, substeps = self.model.mj_model()
        if self._for is not mj_model:
            self.close()
            self._factory = MujocoObjectiveFactory(
                self.model.system, self.task, self.model.nthread, self.discount,
                model=(mj_model, substeps),
            )  # fmt: skip
            self._for = mj_model
        assert self._factory is not None
        return self._factory(q0, qd0, step)

    def close(self) -> None:
        if self._factory is not None:
            self._factory.close()
            self._factory = None


@dataclass
class WhiteBoxConfig(ModelConfig):
    """``model=white_box``: the env's MJCF with parameters identified from the replay buffer
    (`IdentifyConfig`: window, windows, iterations, fd_step), planned on with MuJoCo's
    physics (substeps, integrator: null, the env's)."""

    lr: float | None = None  # no gradient fit
    start: str = rule("documented", choices=("documented", "mjcf"))
    substeps: int | None = rule(None, low=1)  # planning physics steps per control step
    integrator: str | None = rule(None, choices=tuple(MJ_INTEGRATORS))
    window: int = rule(4, low=1)
    windows: int = rule(256, low=1)
    iterations: int = rule(10, low=1)
    fd_step: float = rule(1e-4, low=0, above=True)


@register_model("white_box", schema=WhiteBoxConfig)
def build_white_box(cfg: DictConfig, system: System) -> WhiteBoxModel:
    model = WhiteBoxModel(
        system,
        physics=PlanPhysics(cfg.substeps, cfg.integrator),
        identify=IdentifyConfig(cfg.window, cfg.windows, cfg.iterations, cfg.fd_step),
        nthread=mujoco_threads(),
    )
    if cfg.start == "documented":
        model.set_multipliers(model.white.documented_start())
    return model
