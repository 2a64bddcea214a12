"""Residuals of the humanoid stand and walk tasks for the iLQR oracle (`MujocoILQR`).

The task's reward is a product of saturating factors (head height, torso upright, small
control, still or moving); iLQR needs a least-squares cost that keeps pulling where they
saturate. The residuals, each weighted per its unit (`HumanoidCostWeights`):

- height: head height minus its height at the model's standing pose `qpos0` (m);
- upright: the world x, y of the torso's up axis (0 when upright);
- velocity: the centre of mass's world x, y velocity minus (`speed`, 0) (stand: (0, 0)), m/s;
- balance: the capture point of the centre of mass, its x, y plus `capture_time` times its
  velocity, minus the mean x, y of the feet (m): the feet stay under the body, or step;
- posture: the joints' angles minus `qpos0`'s (rad), and their velocities (rad/s).

Jacobians (tangent space): heights and positions from `mj_jacBody`, `mj_jacSubtreeCom`; the
up axis u turns with the torso's angular Jacobian, du = -[u]x J_r dq; a velocity J(q) qd gets
J on qd (its change with q is left out, the Gauss-Newton approximation).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from mbrl_delan.objectives.mujoco import ENV_PHYSICS, PlanPhysics
from mbrl_delan.planners.ilqr import (
    ILQRPlanner,
    ILQRSettings,
    ILQRStarts,
    MujocoILQR,
    set_kinematics,
)
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.humanoid import HumanoidTask


@dataclass(frozen=True)
class HumanoidCostWeights:
    """Weights of the humanoid residuals (per squared unit) and the capture time."""

    height: float = 100.0  # per m^2
    upright: float = 30.0
    velocity: float = 5.0  # per (m/s)^2
    balance: float = 10.0  # per m^2
    posture: float = 0.3  # per rad^2
    joint_velocity: float = 0.01  # per (rad/s)^2
    capture_time: float = 0.3  # s: the balance point leads the centre of mass by v * this

    def __post_init__(self) -> None:
        values = np.array(list(vars(self).values()), dtype=float)
        if not np.all(np.isfinite(values)) or values.min() < 0:
            raise ValueError(f"humanoid cost weights must be finite and >= 0, got {self}")


class HumanoidResidual:
    """`ResidualCost` of a `HumanoidTask` (stand or walk) on its MuJoCo model.

    Args:
        model: the humanoid's MuJoCo model (free root first).
        task: the task (head, torso and feet, walking speed).
        weights: the residuals' weights.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        task: HumanoidTask,
        weights: HumanoidCostWeights = HumanoidCostWeights(),
    ) -> None:
        self.model, self.data = model, mujoco.MjData(model)
        feet = task.body.feet
        self.feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f) for f in feet]
        if not self.feet or min(self.feet) < 0:
            raise ValueError(f"the task's foot bodies {feet} are not all in the model")
        self.head, self.torso, self.w = task.head, task.torso, weights
        self.head_offset = np.asarray(task.body.head_offset, float)
        self.torso_up = np.asarray(task.body.torso_up, float)
        self.target_velocity = np.array([task.speed or 0.0, 0.0])
        self.qpos0 = model.qpos0.copy()
        set_kinematics(self.model, self.data, self.qpos0)
        self.stand_height = self._head()[2]
        nj = model.nv - 6
        self.weights = np.concatenate([
            [weights.height], np.full(2, weights.upright), np.full(2, weights.velocity),
            np.full(2, weights.balance), np.full(nj, weights.posture),
            np.full(nj, weights.joint_velocity),
        ])  # fmt: skip

    def _head(self) -> np.ndarray:
        return (
            self.data.xpos[self.head] + self.data.xmat[self.head].reshape(3, 3) @ self.head_offset
        )

    def _up(self) -> np.ndarray:
        return self.data.xmat[self.torso].reshape(3, 3) @ self.torso_up

    def _jacobians(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(3, nv) each: the head point, the torso's rotation, the centre of mass, the feet's
        mean position, at the kinematics in self.data."""
        nv = self.model.nv
        head, torso_rot = np.zeros((3, nv)), np.zeros((3, nv))
        mujoco.mj_jac(self.model, self.data, head, None, self._head(), self.head)
        mujoco.mj_jacBody(self.model, self.data, None, torso_rot, self.torso)
        com = np.zeros((3, nv))
        mujoco.mj_jacSubtreeCom(self.model, self.data, com, 1)
        feet = np.zeros((3, nv))
        for foot in self.feet:
            jac = np.zeros((3, nv))
            mujoco.mj_jacBody(self.model, self.data, jac, None, foot)
            feet += jac / len(self.feet)
        return head, torso_rot, com, feet

    def residual(self, q: np.ndarray, qd: np.ndarray, step: int) -> np.ndarray:
        """e (R,): height, upright, velocity, balance, posture, joint velocities. Leaves the
        kinematics of q in self.data."""
        set_kinematics(self.model, self.data, q)
        _, _, com_jac, _ = self._jacobians()
        com_velocity = (com_jac @ qd)[:2]
        com = self.data.subtree_com[1, :2]
        feet = self.data.xpos[self.feet, :2].mean(axis=0)
        joints = np.empty(self.model.nv)
        mujoco.mj_differentiatePos(self.model, joints, 1.0, self.qpos0, q)
        return np.concatenate([
            [self._head()[2] - self.stand_height], self._up()[:2],
            com_velocity - self.target_velocity,
            com + self.w.capture_time * com_velocity - feet, joints[6:], qd[6:],
        ])  # fmt: skip

    def jacobian(self, q: np.ndarray, qd: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        """e (R,) and de/d(dq, dqd) (R, 2 nv)."""
        e = self.residual(q, qd, step)  # leaves the kinematics of q in self.data
        nv = self.model.nv
        head, torso_rot, com, feet = self._jacobians()
        up = self._up()
        skew = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
        J = np.zeros((e.size, 2 * nv))
        J[0, :nv] = head[2]
        J[1:3, :nv] = (-skew @ torso_rot)[:2]
        J[3:5, nv:] = com[:2]
        J[5:7, :nv] = (com - feet)[:2]
        J[5:7, nv:] = self.w.capture_time * com[:2]
        J[7 : 7 + nv - 6, 6:nv] = np.eye(nv - 6)
        J[7 + nv - 6 :, nv + 6 :] = np.eye(nv - 6)
        return e, J


HUMANOID_ILQR = ILQRSettings(horizon=30, iterations=2, control_weight=1e-2, regularization=1.0)


def humanoid_ilqr_policy(
    system: System,
    task: HumanoidTask,
    nthread: int = 1,
    settings: ILQRSettings = HUMANOID_ILQR,
    weights: HumanoidCostWeights = HumanoidCostWeights(),
    physics: PlanPhysics = ENV_PHYSICS,
) -> PlannerPolicy:
    """Receding-horizon iLQR on `system`'s MuJoCo model (stepped as `physics` says) with the
    humanoid residuals of `task`. Close it with `policy.planner.close()`."""
    model, substeps = physics.model(system)
    cost = HumanoidResidual(model, task, weights)
    low, high = system.ctrl_low.numpy(), system.ctrl_high.numpy()
    ilqr = MujocoILQR(model, substeps, low, high, cost, settings, nthread=nthread)
    return PlannerPolicy(ILQRPlanner(ilqr), ILQRStarts(ilqr), action_dtype=torch.float32)
