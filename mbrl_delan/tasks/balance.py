"""A humanoid's planning cost with balance (`BalanceCost`), apart from the task's reward.

The stand and walk rewards (`HumanoidTask`) are products of saturating factors: near upright
they barely change, so a sampling planner with few samples cannot tell a plan that keeps the
body over its feet from one that starts a fall it sees too late. `BalanceCost` is a task for
planning only: its reward is minus a sum of weighted squared terms of the reached state and the
action, each with its unit (`BalanceWeights`), and it never terminates (a fall keeps costing):

- height: (h_head - z_feet - H)^2, H the head's height above the feet at the model's
  standing pose `qpos0` (m);
- balance: |x_cp - x_s|^2 over x, y, the capture point x_cp = x_com + v_com sqrt(z / g) of
  the centre of mass at height z above the feet (where the body would have to step to stop),
  x_s the nearest point to it of the support: the stretch of `support_span` times the segment
  between two feet about their midpoint (0: the midpoint itself, the stand's; 1: the whole
  segment, the walk's, so a step forward carries the support ahead) (m);
- upright: 1 - u_z, u_z the world z of the torso's up axis (0 upright, 2 upside down);
- com_velocity: |v_com,xy - v_target|^2 (m/s), v_target 0 to stand, (speed, 0) to walk
  along x: the task's speed, or the one given (a planner that falls short of the task's speed
  can ask for more);
- heading: 1 - f_x, f_x the world x of the torso's body x axis (Humanoid-v5's forward: 0
  facing the walk's +x, 2 facing back);
- feet_velocity: |v_feet,xy - v_com,xy|^2 ((m/s)^2), v_feet the velocity of the feet's
  midpoint: on a walk, the feet go along with the body (stepping) instead of the body leaning
  ahead of them;
- joint_velocity: mean over the joints of qd^2 ((rad/s)^2);
- posture: mean over the joints of (q - q_0)^2 (rad^2), q_0 the standing pose;
- control: mean of (a / a_max)^2.

The centre of mass and its velocity come from the MJCF's body masses and centres (the nominal
model a user has) over the package's torch forward kinematics, so every world model's imagined
states are scored by it: the momentum is sum_v qd_v (a_v x (h_v - m_v p_v)) for a DoF turning
about axis a_v through p_v, or qd_v m_v a_v for one sliding along a_v, m_v and h_v the mass and
first moment (sum of m_b c_b) of the bodies the DoF moves; the velocity is that over the total
mass. A foot's velocity is sum_v qd_v (a_v x (x_f - p_v)) (turning) or qd_v a_v (sliding) over
the DoFs that move it. On MuJoCo (the oracle) the same body state comes from sensors of the
planning model (`add_sensors`), computed during the rollouts.

The weights (`BalanceWeights`) are the stand's (`STAND_WEIGHTS`) or, for a task with a speed,
the walk's (`WALK_WEIGHTS`: the speed weighs more, the torso faces +x and the feet go along).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import mujoco
import numpy as np
import torch
from torch import Tensor

from mbrl_delan.systems.forward_kinematics import Poses, turn
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import PlacedConstants
from mbrl_delan.tasks.humanoid import HumanoidTask

PLAN_COSTS = ("reward", "balance")  # what planners maximise: the task's reward, or this cost


@dataclass(frozen=True)
class BalanceWeights:
    """Weights of `BalanceCost`'s terms, each per squared unit of its term."""

    height: float = 30.0  # per m^2
    balance: float = 30.0  # per m^2
    upright: float = 3.0  # per unit of 1 - u_z
    heading: float = 0.0  # per unit of 1 - f_x
    com_velocity: float = 1.0  # per (m/s)^2
    feet_velocity: float = 0.0  # per (m/s)^2
    joint_velocity: float = 0.01  # per (rad/s)^2
    posture: float = 0.1  # per rad^2
    control: float = 0.1  # per (a / a_max)^2

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"balance weight {f.name} must be finite and >= 0, got {value}")


# the weights measured on humanoid_stand and humanoid_walk (docs/humanoid.md)
STAND_WEIGHTS = BalanceWeights()
WALK_WEIGHTS = BalanceWeights(heading=10.0, com_velocity=20.0, feet_velocity=2.0)


@dataclass
class CentreOfMass:
    """The whole body's centre of mass (..., 3) and its velocity (..., 3), world frame."""

    position: Tensor
    velocity: Tensor


@dataclass
class BodyState:
    """What the cost reads of a configuration besides q, qd: the head's height (...), the world
    z of the torso's up axis (...) and the world x of its forward axis (...), each foot's
    origin (..., nfeet, 3), the velocity of their midpoint (..., 3), and the centre of mass."""

    head_z: Tensor
    up_z: Tensor
    forward_x: Tensor
    feet: Tensor
    feet_velocity: Tensor
    com: CentreOfMass


SENSOR_PREFIX = "balance_"  # the sites and sensors `add_sensors` puts in a planning model


class BalanceCost(Task):
    """Minus the balance cost of a humanoid `task` (module docstring), for planning only.

    The body state comes from the torch forward kinematics (`body_state`) or, on MuJoCo, from
    sensors the oracle's planning model carries (`add_sensors`, `sensed_reward`: the same
    values, computed by MuJoCo during its rollouts instead of by torch after them).

    Args:
        model: the humanoid's MuJoCo model (the masses and the standing pose it gives).
        task: the evaluated task (its head, torso, feet, speed, control range and episode).
        weights: the terms' weights (None: the stand's, or the walk's for a task with a speed).
        support_span: the share of the segment between the feet that supports the capture
            point at no cost (None: 0 to stand, 1 to walk; module docstring).
        speed: the com_velocity term's target speed along x, m/s (None: the task's, 0 to
            stand); only a task with a speed (a walk) takes one.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        task: HumanoidTask,
        weights: BalanceWeights | None = None,
        support_span: float | None = None,
        speed: float | None = None,
    ) -> None:
        names = task.body.feet
        feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f) for f in names]
        if not feet or min(feet) < 0:
            raise ValueError(f"the task's foot bodies {names} are not all in the model")
        walk = task.speed is not None
        if speed is not None and not (walk and math.isfinite(speed) and speed >= 0):
            raise ValueError(f"a planning speed needs a walking task and a finite speed >= 0, "
                             f"got {speed} for {task.name}")  # fmt: skip
        if weights is None:
            weights = WALK_WEIGHTS if walk else STAND_WEIGHTS
        span = (1.0 if walk else 0.0) if support_span is None else support_span
        target = (task.speed or 0.0) if speed is None else speed
        if not 0.0 <= span <= 1.0:
            raise ValueError(f"support_span must be in [0, 1], got {support_span}")
        self.task, self.weights, self.feet, self.support_span = task, weights, feet, span
        self.name, self.episode_len = f"{task.name}_balance", task.episode_len
        self.gravity = float(np.linalg.norm(model.opt.gravity))
        if self.gravity <= 0:
            raise ValueError("a balance cost needs gravity (the capture point's sqrt(z / g))")
        self.total_mass = float(model.body_mass.sum())
        moves = np.array([[_below(model.body_parentid, b, self.task.fk.dof_body[v])
                           for b in range(model.nbody)] for v in range(model.nv)])  # fmt: skip
        self.constants = PlacedConstants(
            mass=torch.from_numpy(model.body_mass.copy()),  # (nbody,)
            centre=torch.from_numpy(model.body_ipos.copy()),  # (nbody, 3) in the body frame
            moves=torch.from_numpy(moves.astype(np.float64)),  # (nv, nbody)
            foot_moves=torch.from_numpy(moves[:, feet].astype(np.float64)),  # (nv, nfeet)
            rotational=torch.tensor(task.fk.rotational),  # (nv,) bool
            qpos0=task.qpos0.clone(),  # (nq,)
            target_velocity=torch.tensor([target, 0.0], dtype=torch.float64),
        )
        q0 = task.qpos0.unsqueeze(0)
        standing = self.body_state(q0, q0.new_zeros(1, model.nv))
        self.stand_height = float(standing.head_z[0] - standing.feet[0, :, 2].mean())

    def centre_of_mass(self, q: Tensor, qd: Tensor, poses: Poses | None = None,
                       axes: tuple[Tensor, Tensor] | None = None) -> CentreOfMass:  # fmt: skip
        """The centre of mass and its velocity at (q (..., nq), qd (..., nv))."""
        if poses is None or axes is None:
            poses, dof = self.task.fk.dof_axes(q)
            axes = (dof.axis, dof.anchor)
        c = self.constants.on(q)
        centres = poses.xpos + turn(poses.xmat, c["centre"])  # (..., nbody, 3)
        moment = c["mass"].unsqueeze(-1) * centres  # (..., nbody, 3)
        axis, anchor = axes  # (..., nv, 3) each
        moved_moment = torch.einsum("vb,...bk->...vk", c["moves"], moment)  # (..., nv, 3)
        moved_mass = (c["moves"] * c["mass"]).sum(-1).unsqueeze(-1)  # (nv, 1)
        spin = torch.linalg.cross(axis, moved_moment - moved_mass * anchor, dim=-1)
        per_dof = torch.where(c["rotational"].unsqueeze(-1), spin, moved_mass * axis)
        momentum = (per_dof * qd.unsqueeze(-1)).sum(-2)  # (..., 3)
        return CentreOfMass(moment.sum(-2) / self.total_mass, momentum / self.total_mass)

    def feet_velocity(self, feet: Tensor, qd: Tensor, axes: tuple[Tensor, Tensor]) -> Tensor:
        """The mean velocity (..., 3) of the feet's origins `feet` (..., nfeet, 3) at qd
        (..., nv), each DoF's world axis and anchor `axes` ((..., nv, 3) each)."""
        c = self.constants.on(qd)
        axis, anchor = axes
        lever = feet.unsqueeze(-3) - anchor.unsqueeze(-2)  # (..., nv, nfeet, 3)
        slide = axis.unsqueeze(-2).expand_as(lever)
        spin = torch.linalg.cross(slide, lever, dim=-1)
        per_dof = torch.where(c["rotational"][:, None, None], spin, slide)
        moved = per_dof * (c["foot_moves"].unsqueeze(-1) * qd[..., None, None])
        return moved.sum(-3).mean(-2)

    def body_state(self, q: Tensor, qd: Tensor) -> BodyState:
        """The body state at (q (..., nq), qd (..., nv)) by the torch forward kinematics."""
        poses, dof = self.task.fk.dof_axes(q)
        axes = (dof.axis, dof.anchor)
        com = self.centre_of_mass(q, qd, poses, axes)
        feet = poses.xpos[..., self.feet, :]  # (..., nfeet, 3)
        forward_x = poses.xmat[..., self.task.torso, 0, 0]
        return BodyState(self.task._head_z(poses), self.task._up_z(poses), forward_x, feet,
                         self.feet_velocity(feet, qd, axes), com)  # fmt: skip

    def add_sensors(self, spec: mujoco.MjSpec) -> None:
        """Put the body state's sensors last in a planning model's `spec`: the head point and
        the torso's up axis (sites on the torso), the centre of mass and its velocity (of the
        root's subtree), each foot's origin and its velocity, and the torso's forward axis;
        `sensed_state` reads them."""
        body, site = self.task.body, mujoco.mjtObj.mjOBJ_SITE
        head = spec.body(body.head_body).add_site(
            name=f"{SENSOR_PREFIX}head", pos=list(body.head_offset)
        )
        up = spec.body(body.torso_body).add_site(
            name=f"{SENSOR_PREFIX}up", quat=_z_to(np.asarray(body.torso_up, float))
        )
        root = spec.bodies[1].name
        sensors = [
            (mujoco.mjtSensor.mjSENS_FRAMEPOS, site, head.name),
            (mujoco.mjtSensor.mjSENS_FRAMEZAXIS, site, up.name),
            (mujoco.mjtSensor.mjSENS_SUBTREECOM, mujoco.mjtObj.mjOBJ_BODY, root),
            (mujoco.mjtSensor.mjSENS_SUBTREELINVEL, mujoco.mjtObj.mjOBJ_BODY, root),
        ] + [(kind, mujoco.mjtObj.mjOBJ_XBODY, f)
             for kind in (mujoco.mjtSensor.mjSENS_FRAMEPOS, mujoco.mjtSensor.mjSENS_FRAMELINVEL)
             for f in body.feet]  # fmt: skip
        sensors.append((mujoco.mjtSensor.mjSENS_FRAMEXAXIS, mujoco.mjtObj.mjOBJ_XBODY,
                        body.torso_body))  # fmt: skip
        for i, (kind, objtype, name) in enumerate(sensors):
            spec.add_sensor(name=f"{SENSOR_PREFIX}{i}", type=kind, objtype=objtype, objname=name)

    @property
    def sensor_size(self) -> int:
        """The sensor values `add_sensors` adds."""
        return 3 * (5 + 2 * len(self.feet))

    def sensed_state(self, sensed: Tensor) -> BodyState:
        """The body state from the last `sensor_size` sensor values (..., nsensordata)."""
        values = sensed[..., -self.sensor_size :]
        feet = values[..., 12:-3].unflatten(-1, (2, len(self.feet), 3))  # (..., 2, nfeet, 3)
        com = CentreOfMass(values[..., 6:9], values[..., 9:12])
        return BodyState(values[..., 2], values[..., 5], values[..., -3], feet[..., 0, :, :],
                         feet[..., 1, :, :].mean(-2), com)  # fmt: skip

    def capture_point(self, com: CentreOfMass, ground: Tensor) -> Tensor:
        """x, y of the capture point x_com + v_com sqrt(z / g), z the centre of mass's height
        above `ground` (...). -> (..., 2)"""
        z = torch.clamp(com.position[..., 2] - ground, min=0.0)
        lead = torch.sqrt(z / self.gravity).unsqueeze(-1)
        return com.position[..., :2] + com.velocity[..., :2] * lead

    def support_point(self, feet: Tensor, point: Tensor) -> Tensor:
        """The point of the support (module docstring) nearest to `point` (..., 2), x, y, for
        the feet's origins `feet` (..., nfeet, 3). -> (..., 2)"""
        middle = feet[..., :2].mean(-2)
        if self.support_span == 0.0 or feet.shape[-2] != 2:
            return middle
        half = 0.5 * (feet[..., 1, :2] - feet[..., 0, :2])  # (..., 2)
        along = ((point - middle) * half).sum(-1) / half.square().sum(-1).clamp(min=1e-12)
        reach = torch.clamp(along, -self.support_span, self.support_span)
        return middle + reach.unsqueeze(-1) * half

    def terms_of(self, body: BodyState, q: Tensor, qd: Tensor, action: Tensor
                 ) -> dict[str, Tensor]:  # fmt: skip
        """Each term of the cost, unweighted, at a body state. -> {name: (...)}"""
        c = self.constants.on(q)
        ground = body.feet[..., 2].mean(-1)
        capture = self.capture_point(body.com, ground)
        return {
            "height": (body.head_z - ground - self.stand_height).square(),
            "balance": (capture - self.support_point(body.feet, capture)).square().sum(-1),
            "upright": 1.0 - body.up_z,
            "heading": 1.0 - body.forward_x,
            "com_velocity": (body.com.velocity[..., :2] - c["target_velocity"]).square().sum(-1),
            "feet_velocity": (body.feet_velocity - body.com.velocity)[..., :2].square().sum(-1),
            "joint_velocity": qd[..., 6:].square().mean(-1),
            "posture": (q[..., 7:] - c["qpos0"][7:]).square().mean(-1),
            "control": (action / self.task.ctrl_max).square().mean(-1),
        }

    def terms(self, q: Tensor, qd: Tensor, action: Tensor) -> dict[str, Tensor]:
        """Each term of the cost, unweighted. (..., nq), (..., nv), (..., nu) -> {name: (...)}"""
        return self.terms_of(self.body_state(q, qd), q, qd, action)

    def _weighted(self, terms: dict[str, Tensor]) -> Tensor:
        return sum(getattr(self.weights, name) * value for name, value in terms.items())

    def cost(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """The weighted sum of the terms. -> (...)"""
        return self._weighted(self.terms(q, qd, action))

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        return -self.cost(q, qd, action)

    def sensed_reward(self, sensed: Tensor, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """`reward` with the body state from the planning model's sensors (..., nsensordata)."""
        return -self._weighted(self.terms_of(self.sensed_state(sensed), q, qd, action))

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        return self.task.initial_state(batch_shape, generator)


def _z_to(axis: np.ndarray) -> list[float]:
    """The unit quaternion (w, x, y, z) that turns +z onto the unit vector `axis`."""
    z = np.array([0.0, 0.0, 1.0])
    quat = np.concatenate([[1.0 + z @ axis], np.cross(z, axis)])
    if np.linalg.norm(quat) < 1e-9:  # axis = -z: half a turn about x
        return [0.0, 1.0, 0.0, 0.0]
    return list(quat / np.linalg.norm(quat))


def _below(parent: np.ndarray, body: int, ancestor: int) -> bool:
    """Is `body` `ancestor` itself or below it in the tree."""
    while body > 0 and body != ancestor:
        body = int(parent[body])
    return body == ancestor
