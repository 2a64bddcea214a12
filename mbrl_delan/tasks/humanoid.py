"""Humanoid tasks: stand and walk, as pure torch functions of (q, qd, action).

Each reward is a product of factors in [0, 1] (1 is best), computed through the torch forward
kinematics (`ForwardKinematics`), so thousands of imagined states score in one call:

- standing = tolerance_below(head height, stand_height, margin stand_height / 4);
- upright = (1 + tolerance_below(up_z, 0.9, margin 1.9)) / 2, up_z the world z of the torso's
  up axis (1 upright, 0 lying, -1 upside down);
- small_control = (4 + exp(-mean((a / a_max)^2))) / 5;
- stand: still = mean over x, y of 0.1^((v / 2)^2), v the root's world-frame velocity;
  walk: moving = (1 + 5 clamp(|v_xy| / speed, 0, 1)) / 6.

`tolerance_below(x, lower, margin) = 0.1^(d^2)` with d = max(lower - x, 0) / margin: 1 at or
above `lower`, 0.1 one margin below it. An episode terminates when the head drops below
`fall_height` (the humanoid has fallen; imagined rollouts stop scoring there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import torch
from torch import Tensor

from mbrl_delan.systems.forward_kinematics import ForwardKinematics, Poses
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import PlacedConstants

MARGIN_VALUE = 0.1  # a tolerance factor's value one margin away from its bound


def tolerance_below(x: Tensor, lower: float, margin: float) -> Tensor:
    """1 for x >= lower, falling as 0.1^(d^2), d = (lower - x) / margin below it. (...) -> (...)"""
    d = torch.clamp(lower - x, min=0.0) / margin
    return torch.exp(math.log(MARGIN_VALUE) * d.square())


@dataclass(frozen=True)
class HumanoidBody:
    """Where a humanoid's head and torso are in its MuJoCo model."""

    head_body: str
    head_offset: tuple[float, float, float]  # head point in the head body's frame
    torso_body: str
    torso_up: tuple[float, float, float]  # the torso's up axis in its own frame
    feet: tuple[str, ...] = ()  # the foot bodies (the iLQR oracle's balance residual)


# gymnasium's Humanoid-v5: the head is a sphere geom on the torso, z up
HUMANOID_V5_BODY = HumanoidBody(
    "torso", (0.0, 0.0, 0.19), "torso", (0.0, 0.0, 1.0), ("left_foot", "right_foot")
)
# dm_control's CMU humanoid: a head body; its body frames are y up
HUMANOID_CMU_BODY = HumanoidBody(
    "head", (0.0, 0.11, 0.03), "thorax", (0.0, 1.0, 0.0), ("lfoot", "rfoot")
)


class HumanoidTask(Task):
    """Stand (`speed` None) or walk at `speed` m/s on a humanoid with a free root joint.

    Args:
        model: the humanoid's MuJoCo model (its free joint first: q[0:7], qd[0:6]).
        body: where the head and torso are (`HUMANOID_V5_BODY`, `HUMANOID_CMU_BODY`).
        speed: walking speed target in m/s; None: stand still.
        stand_height: head height (m) that counts as standing.
        fall_height: head height (m) below which an episode terminates; None: never.
        ctrl_max: largest |action| per actuator (normalises the control cost).
        episode_len: control steps per episode.
        reset_noise: half-width of the uniform noise on q and qd at reset (gymnasium's 0.01).
        name: task name.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        body: HumanoidBody,
        speed: float | None = None,
        stand_height: float = 1.4,
        fall_height: float | None = 0.7,
        ctrl_max: float = 1.0,
        episode_len: int = 1000,
        reset_noise: float = 0.01,
        name: str = "humanoid_stand",
    ) -> None:
        if model.njnt == 0 or model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError("a humanoid task needs a free root joint first in the model")
        if speed is not None and speed <= 0:
            raise ValueError(f"speed must be > 0 m/s (or None to stand), got {speed}")
        self.fk = ForwardKinematics.from_mujoco(model)
        self.head = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body.head_body)
        self.torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body.torso_body)
        if min(self.head, self.torso) < 0:
            raise ValueError(f"bodies {body.head_body!r} / {body.torso_body!r} not in the model")
        self.nbody = max(self.head, self.torso) + 1  # the bodies the rewards need (tree order)
        self.body, self.speed = body, speed
        self.stand_height, self.fall_height = stand_height, fall_height
        self.ctrl_max, self.episode_len, self.reset_noise = ctrl_max, episode_len, reset_noise
        self.qpos0 = torch.from_numpy(model.qpos0.copy())  # (nq,) float64
        self.constants = PlacedConstants(
            head_offset=torch.tensor(body.head_offset, dtype=torch.float64),  # (3,)
            torso_up=torch.tensor(body.torso_up, dtype=torch.float64),  # (3,)
        )
        self.nv, self.name = model.nv, name

    def _head_z(self, poses: Poses) -> Tensor:
        """Head height (...) in m."""
        pos, mat = poses.xpos[..., self.head, :], poses.xmat[..., self.head, :, :]
        offset = self.constants.on(pos)["head_offset"]
        return pos[..., 2] + (mat[..., 2, :] * offset).sum(-1)

    def _up_z(self, poses: Poses) -> Tensor:
        """World z of the torso's up axis (...), in [-1, 1]."""
        mat = poses.xmat[..., self.torso, :, :]
        up = self.constants.on(mat)["torso_up"]
        return (mat[..., 2, :] * up).sum(-1)

    def _poses(self, q: Tensor) -> Poses:
        """Poses of the head, the torso and the bodies before them. (..., nq) ->"""
        return self.fk(q, self.nbody)

    def head_height(self, q: Tensor) -> Tensor:
        """(..., nq) -> (...) m."""
        return self._head_z(self._poses(q))

    def upright(self, q: Tensor) -> Tensor:
        """World z of the torso's up axis, in [-1, 1]. (..., nq) -> (...)."""
        return self._up_z(self._poses(q))

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        poses = self._poses(q)
        standing = tolerance_below(self._head_z(poses), self.stand_height, self.stand_height / 4)
        upright = (1.0 + tolerance_below(self._up_z(poses), 0.9, 1.9)) / 2.0
        control = torch.exp(-(action / self.ctrl_max).square().mean(dim=-1))
        small_control = (4.0 + control) / 5.0
        return standing * upright * small_control * self._motion(qd[..., 0:2])

    def _motion(self, velocity_xy: Tensor) -> Tensor:
        """Stand: still; walk: moving at `speed`. (..., 2) -> (...)"""
        if self.speed is None:
            return torch.exp(math.log(MARGIN_VALUE) * (velocity_xy / 2.0).square()).mean(-1)
        progress = torch.clamp(torch.linalg.vector_norm(velocity_xy, dim=-1) / self.speed, 0, 1)
        return (1.0 + 5.0 * progress) / 6.0

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        if self.fall_height is None:
            return super().terminated(q, qd)
        return self.head_height(q) < self.fall_height

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        """qpos0 and rest, each entry moved by U(-reset_noise, reset_noise); unit root quat."""
        kwargs = {"generator": generator, "dtype": torch.float64, "device": generator.device}
        q0 = self.qpos0.to(generator.device)
        noise = self.reset_noise * (2 * torch.rand((*batch_shape, q0.shape[0]), **kwargs) - 1)
        q = q0 + noise
        quat = q[..., 3:7] / torch.linalg.vector_norm(q[..., 3:7], dim=-1, keepdim=True)
        q = torch.cat([q[..., :3], quat, q[..., 7:]], dim=-1)
        qd = self.reset_noise * (2 * torch.rand((*batch_shape, self.nv), **kwargs) - 1)
        return State(q=q, qd=qd)
