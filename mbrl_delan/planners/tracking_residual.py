"""Residuals of a motion-tracking task for the iLQR oracle (`MujocoILQR`).

`MotionTracking`'s reward sums w exp(-k |e|^2) over four terms; near the reference,
1 - reward ~ sum w k |e|^2, so its residuals weighted w k are the reward's own quadratic
cost (halved). Exponentials saturate far from the reference, where a squared cost keeps
pulling; iLQR uses the squared form:

- pose: q (-) q_ref over the rotational DoFs (root rotation vector, hinges), weight w k;
- velocity: qd - qd_ref over the same DoFs, weight w k;
- end effectors: world positions relative to the root minus the reference's, weight w k;
- root: the root position minus the reference's, weight w k (`root_weight` overrides);
- body points: world positions of `point_bodies` minus the reference's, weight
  `point_weight` per m^2 (0: off). They hold the whole body, pelvis included, in place;
- body velocities: world linear velocities of the same bodies minus the reference's
  (J_b(q_ref) qd_ref), weight `point_velocity_weight` per (m/s)^2 (0: off).

Jacobians (tangent space): the pose and velocity rows are the identity on their DoFs (exact
for hinges; the Gauss-Newton approximation of the root rotation's), the point rows come from
`mj_jacBody`; a body velocity J_b(q) qd gets J_b on qd (its change with q is left out).
"""

from __future__ import annotations

from collections.abc import Sequence
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
from mbrl_delan.tasks.tracking import MotionTracking

# pelvis, head, toes, feet, shins, hands, forearms, upper arms, thighs (CMU humanoid)
CMU_BODY_POINTS = (
    "root", "head", "ltoes", "rtoes", "lfoot", "rfoot", "ltibia", "rtibia", "lhand", "rhand",
    "lradius", "rradius", "lhumerus", "rhumerus", "lfemur", "rfemur",
)  # fmt: skip


class TrackingResidual:
    """`ResidualCost` of a `MotionTracking` task on its MuJoCo model.

    Args:
        model: the task's MuJoCo model (free root first).
        task: the tracking task (reference, end effectors, weights and scales).
        point_bodies: bodies scored by their world position.
        point_weight: weight of each body point's squared error (per m^2); 0 turns them off.
        root_weight: weight of the root term (None: the task's w k).
        point_velocity_weight: weight of each body's squared velocity error (per (m/s)^2);
            0 turns them off.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        task: MotionTracking,
        point_bodies: Sequence[str] = CMU_BODY_POINTS,
        point_weight: float = 0.0,
        root_weight: float | None = None,
        point_velocity_weight: float = 0.0,
    ) -> None:
        given = (point_weight, point_velocity_weight, 0.0 if root_weight is None else root_weight)
        if not all(np.isfinite(given)) or min(given) < 0:
            raise ValueError(
                "point_weight, point_velocity_weight and root_weight must be finite and >= 0, "
                f"got {point_weight}, {point_velocity_weight}, {root_weight}"
            )
        self.model, self.data = model, mujoco.MjData(model)
        self.ref_q, self.ref_qd = task.ref_q.numpy(), task.ref_qd.numpy()  # (T+1, nq), (T+1, nv)
        self.last = self.ref_q.shape[0] - 1
        self.root_body = task.root_body
        self.ee_bodies = task.bodies.tolist()
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in point_bodies]
        missing = [n for n, i in zip(point_bodies, ids, strict=True) if i < 0]
        if missing:
            raise ValueError(f"body points not in the model: {', '.join(missing)}")
        self.points = ids if point_weight > 0 else []
        self.moving = ids if point_velocity_weight > 0 else []  # bodies scored by velocity
        self.ref_points, self.ref_velocities = [], []
        for q, qd in zip(self.ref_q, self.ref_qd, strict=True):
            set_kinematics(self.model, self.data, q)
            self.ref_points.append(self._points())
            self.ref_velocities.append(self._velocities(qd))
        w, k, nv = task.weights, task.scales, model.nv
        root = w.root * k.root if root_weight is None else root_weight
        self.weights = np.concatenate([
            np.full(nv - 3, w.pose * k.pose), np.full(nv - 3, w.velocity * k.velocity),
            np.full(3 * len(self.ee_bodies), w.end_effector * k.end_effector), np.full(3, root),
            np.full(3 * len(self.points), point_weight),
            np.full(3 * len(self.moving), point_velocity_weight),
        ])  # fmt: skip

    def _points(self) -> np.ndarray:
        """Root, end effectors relative to it, body points: (1 + E + P, 3) world positions
        at the kinematics in self.data."""
        xpos = self.data.xpos
        root = xpos[self.root_body]
        return np.concatenate([root[None], xpos[self.ee_bodies] - root, xpos[self.points]])

    def _body_jacobian(self, body: int) -> np.ndarray:
        """Translational Jacobian (3, nv) of `body`'s origin at the kinematics in self.data."""
        jac = np.zeros((3, self.model.nv))
        mujoco.mj_jacBody(self.model, self.data, jac, None, body)
        return jac

    def _velocities(self, qd: np.ndarray) -> np.ndarray:
        """World linear velocities (B, 3) of the bodies scored by velocity (B may be 0), at
        the kinematics in self.data."""
        if not self.moving:
            return np.zeros((0, 3))
        return np.stack([self._body_jacobian(b) @ qd for b in self.moving])

    def residual(self, q: np.ndarray, qd: np.ndarray, step: int) -> np.ndarray:
        """e (R,): pose, velocity, end effectors, root, body points, body velocities against
        ref min(step + 1, T). Leaves the kinematics of q in self.data."""
        j = min(step + 1, self.last)
        pose = np.empty(self.model.nv)
        mujoco.mj_differentiatePos(self.model, pose, 1.0, self.ref_q[j], q)
        set_kinematics(self.model, self.data, q)
        velocities = self._velocities(qd) - self.ref_velocities[j]
        points = self._points() - self.ref_points[j]
        ee, rest = points[1 : 1 + len(self.ee_bodies)], points[1 + len(self.ee_bodies) :]
        return np.concatenate([
            pose[3:], (qd - self.ref_qd[j])[3:], ee.ravel(), points[0], rest.ravel(),
            velocities.ravel(),
        ])  # fmt: skip

    def jacobian(self, q: np.ndarray, qd: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        """e (R,) and de/d(dq, dqd) (R, 2 nv)."""
        e = self.residual(q, qd, step)  # leaves the kinematics of q in self.data
        nv, n_vel = self.model.nv, 3 * len(self.moving)
        J = np.zeros((e.size, 2 * nv))
        J[: nv - 3, 3:nv] = np.eye(nv - 3)
        J[nv - 3 : 2 * nv - 6, nv + 3 :] = np.eye(nv - 3)
        root = self._body_jacobian(self.root_body)
        rows = [self._body_jacobian(b) - root for b in self.ee_bodies] + [root]
        rows += [self._body_jacobian(b) for b in self.points]
        J[2 * nv - 6 : e.size - n_vel, :nv] = np.concatenate(rows)
        if n_vel:
            J[e.size - n_vel :, nv:] = np.concatenate([self._body_jacobian(b) for b in self.moving])
        return e, J


@dataclass(frozen=True)
class TrackingCostWeights:
    """What the iLQR oracle's cost adds to a tracking task's own w k terms (`TrackingResidual`)."""

    point: float = 30.0  # per m^2, each body point's world position
    point_velocity: float = 3.0  # per (m/s)^2, each body point's world linear velocity
    root: float | None = 3000.0  # per m^2, the root's position (None: the task's w k): keeps
    # the body from drifting off the clip (the task ends 0.5 m away)


# the iLQR oracle for tracking (measured on four clips in docs/humanoid.md): 3 iterations on
# one set of derivatives per control step
TRACKING_ILQR = ILQRSettings(horizon=20, iterations=3, regularization=10.0, reuse_derivatives=True)


def tracking_ilqr_policy(
    system: System,
    task: MotionTracking,
    nthread: int = 1,
    settings: ILQRSettings = TRACKING_ILQR,
    weights: TrackingCostWeights = TrackingCostWeights(),
    physics: PlanPhysics = ENV_PHYSICS,
) -> PlannerPolicy:
    """Receding-horizon iLQR on `system`'s MuJoCo model (stepped as `physics` says) with
    `task`'s tracking residuals. Close it with `policy.planner.close()` (or leave it to the
    garbage collector)."""
    if not isinstance(task, MotionTracking):
        raise ValueError(f"the iLQR oracle needs a motion-tracking task, got {task.name}")
    model, substeps = physics.model(system)
    cost = TrackingResidual(
        model, task, point_weight=weights.point, root_weight=weights.root,
        point_velocity_weight=weights.point_velocity,
    )  # fmt: skip
    low, high = system.ctrl_low.numpy(), system.ctrl_high.numpy()
    ilqr = MujocoILQR(model, substeps, low, high, cost, settings, nthread=nthread)
    return PlannerPolicy(ILQRPlanner(ilqr), ILQRStarts(ilqr), action_dtype=torch.float32)
