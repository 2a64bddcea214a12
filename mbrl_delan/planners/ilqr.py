"""iLQR on MuJoCo's own dynamics: a gradient-based oracle planner.

The sampling planners see only returns; this one uses the derivatives of the simulator, for
tasks whose cost is a weighted sum of squared residuals (`ResidualCost`):

    J(U) = sum_{t=1..H} 1/2 e(x_t, s + t - 1)^T W e(x_t, s + t - 1) + sum_{t=0..H-1} 1/2 c |u_t|^2

x_t = (q_t, qd_t) the state reached by the first t controls from x_0, s the episode step of
u_0 and c the control weight. Each iteration (Gauss-Newton iLQR):

1. the control-step Jacobians A_t = dx_{t+1}/dx_t (2nv, 2nv) and B_t = dx_{t+1}/du_t (2nv, nu)
   by forward differences, in MuJoCo's tangent space (positions perturbed with
   `mj_integratePos`, compared with `mj_differentiatePos`), all H (1 + 2nv + nu) perturbed
   control steps in one multi-threaded `mujoco.rollout` call;
2. a backward Riccati pass with the cost's Gauss-Newton Hessian J_e^T W J_e and
   Levenberg-Marquardt regularisation mu I on Q_uu, giving feed-forward terms k_t and gains K_t;
3. a forward pass u_t = clip(u_t + alpha k_t + K_t (x_t (-) xbar_t)) on MuJoCo, for alpha in
   `line_search` until the cost falls; mu shrinks after an accepted step and grows when none is
   (the next iteration then reuses the derivatives: the trajectory has not moved). With
   `reuse_derivatives` every iteration of a plan reuses the first one's A_t, B_t: one
   derivative pass per plan, the costliest part.

`ILQRPlanner` runs it under `PlannerPolicy`, warm-started from the previous plan shifted by the
steps executed since, as the sampling planners are.
Everything runs in float64 numpy on the CPU (MuJoCo's side of the oracle).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Protocol

import mujoco
import numpy as np
import torch
from scipy.linalg import cho_factor, cho_solve
from threadpoolctl import ThreadpoolController
from torch import Tensor

from mbrl_delan.objectives.base import ObjectiveFactory
from mbrl_delan.objectives.mujoco import FULLPHYSICS, HeldControlRollout

log = logging.getLogger(__name__)


def set_kinematics(model: mujoco.MjModel, data: mujoco.MjData, q: np.ndarray) -> None:
    """Put the kinematics of q in `data`: body poses, subtree centres of mass and what the
    Jacobians (`mj_jac`, `mj_jacBody`, `mj_jacSubtreeCom`) read."""
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)


class ResidualCost(Protocol):
    """A state cost 1/2 e^T diag(weights) e with residuals e of the state and episode step."""

    weights: np.ndarray  # (R,) >= 0

    def residual(self, q: np.ndarray, qd: np.ndarray, step: int) -> np.ndarray:
        """e (R,) of the state (q (nq,), qd (nv,)) reached by the action of `step`."""
        ...

    def jacobian(self, q: np.ndarray, qd: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        """e (R,) and de/dx (R, 2 nv), x in the tangent space (dq, dqd)."""
        ...


@dataclass(frozen=True)
class ILQRSettings:
    """Sizes and constants of the iLQR planner."""

    horizon: int = 10  # control steps planned
    iterations: int = 2  # iLQR iterations per control step
    control_weight: float = 1e-3  # c in 1/2 c |u|^2 per step
    regularization: float = 1e-3  # mu at the start of each plan
    fd_eps: float = 1e-6  # forward-difference step (tangent space and controls)
    line_search: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.03)
    reuse_derivatives: bool = False  # later iterations of a plan reuse its first A, B

    def __post_init__(self) -> None:
        if self.horizon < 1 or self.iterations < 1:
            raise ValueError(
                f"iLQR horizon and iterations must be >= 1, got {self.horizon}, {self.iterations}"
            )
        positive = (self.regularization, self.fd_eps, *self.line_search)
        if self.control_weight < 0 or not all(np.isfinite(positive)) or min(positive) <= 0:
            raise ValueError(
                "iLQR control_weight must be >= 0 and regularization, fd_eps and the "
                f"line-search steps > 0, got {self}"
            )


@dataclass
class ILQRResult:
    """What one call of `plan` found."""

    actions: np.ndarray  # (H, nu) the plan, within the control range
    cost: float  # its cost J(U)
    initial_cost: float  # J of the warm start
    accepted: int  # iterations whose line search lowered the cost

    @property
    def mean(self) -> Tensor:
        """The plan as `PlannerPolicy` executes it. (H, nu) float64"""
        return torch.from_numpy(self.actions)

    @property
    def best_return(self) -> float:
        return -self.cost


class MujocoILQR:
    """iLQR over a MuJoCo model, each control held for `frame_skip` physics steps.

    Args:
        model: the MuJoCo model (its own timestep and integrator).
        frame_skip: physics steps per control step.
        ctrl_low: the control range's lower bounds (nu,).
        ctrl_high: its upper bounds (nu,).
        cost: the state cost (`ResidualCost`).
        settings: horizon, iterations and constants.
        nthread: MuJoCo rollout threads for the derivatives.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        frame_skip: int,
        ctrl_low: np.ndarray,
        ctrl_high: np.ndarray,
        cost: ResidualCost,
        settings: ILQRSettings = ILQRSettings(),
        nthread: int = 1,
    ) -> None:
        self.model, self.frame_skip, self.cost, self.settings = model, frame_skip, cost, settings
        self.low, self.high = np.asarray(ctrl_low, float), np.asarray(ctrl_high, float)
        self.nq, self.nv, self.nu = model.nq, model.nv, model.nu
        self.sim = HeldControlRollout(model, frame_skip, nthread)
        self.data = mujoco.MjData(model)  # the forward pass's
        # the Riccati pass's matrices are small: BLAS threads only wait on each other, and on
        # a busy CPU for the other processes (20x slower backward passes measured)
        self.blas = ThreadpoolController()

    def close(self) -> None:
        self.sim.close()

    # ------------------------------------------------------------ states
    def full_state(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """FULLPHYSICS state (nstate,) at time 0 with qpos = q, qvel = qd."""
        return self.sim.full_state(q, qd)

    def tangent(self, state: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """state (-) ref in the tangent space: (dq, dqd) (2 nv,)."""
        (q, qd), (q0, qd0) = self.sim.qv(state), self.sim.qv(ref)
        dq = np.empty(self.nv)
        mujoco.mj_differentiatePos(self.model, dq, 1.0, q0, q)
        return np.concatenate([dq, qd - qd0])

    # ------------------------------------------------------------ cost
    def total_cost(self, states: np.ndarray, actions: np.ndarray, step: int) -> float:
        """J of states (H + 1, nstate) x_0..x_H and actions (H, nu) from episode step `step`."""
        w = self.cost.weights
        total = 0.5 * self.settings.control_weight * float(np.sum(actions * actions))
        for t in range(1, states.shape[0]):
            e = self.cost.residual(*self.sim.qv(states[t]), step + t - 1)
            total += 0.5 * float(np.sum(w * e * e))
        return total

    # ------------------------------------------------------------ derivatives
    def derivatives(self, states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward-difference A (H, 2nv, 2nv), B (H, 2nv, nu) of the control-step map along
        states (H + 1, nstate) and actions (H, nu) (within the control range)."""
        horizon, nv, nu, eps = actions.shape[0], self.nv, self.nu, self.settings.fd_eps
        n = 1 + 2 * nv + nu
        init = np.repeat(states[:horizon, None], n, axis=1)  # (H, n, nstate)
        ctrl = np.repeat(actions[:, None], n, axis=1)  # (H, n, nu)
        sign = np.where(actions + eps > self.high, -1.0, 1.0)  # stay inside the range
        for t in range(horizon):
            q = self.sim.qv(states[t])[0]
            for i in range(nv):
                dq = np.zeros(nv)
                dq[i] = eps
                qpos = init[t, 1 + i, self.sim.qpos_at : self.sim.qpos_at + self.nq]
                qpos[:] = q
                mujoco.mj_integratePos(self.model, qpos, dq, 1.0)
                init[t, 1 + nv + i, self.sim.qvel_at + i] += eps
            ctrl[t, 1 + 2 * nv + np.arange(nu), np.arange(nu)] += sign[t] * eps
        end = self.sim(init.reshape(horizon * n, -1), ctrl.reshape(horizon * n, 1, nu))
        end = end[:, 0].reshape(horizon, n, self.sim.nstate)
        A, B = np.empty((horizon, 2 * nv, 2 * nv)), np.empty((horizon, 2 * nv, nu))
        for t in range(horizon):
            cols = np.stack([self.tangent(end[t, c], end[t, 0]) for c in range(1, n)], axis=1)
            A[t] = cols[:, : 2 * nv] / eps
            B[t] = cols[:, 2 * nv :] * (sign[t] / eps)
        return A, B

    # ------------------------------------------------------------ iLQR
    def _backward(
        self, states: np.ndarray, actions: np.ndarray, A: np.ndarray, B: np.ndarray, step: int,
        mu: float,
    ) -> tuple[np.ndarray, np.ndarray] | None:  # fmt: skip
        """Feed-forward k (H, nu) and gains K (H, nu, 2nv); None if Q_uu is not positive."""
        horizon, w, c = actions.shape[0], self.cost.weights, self.settings.control_weight
        e, J = self.cost.jacobian(*self.sim.qv(states[horizon]), step + horizon - 1)
        vx, vxx = J.T @ (w * e), J.T @ (w[:, None] * J)
        k, K = np.empty((horizon, self.nu)), np.empty((horizon, self.nu, 2 * self.nv))
        eye = np.eye(self.nu)
        for t in range(horizon - 1, -1, -1):
            qx, qxx = A[t].T @ vx, A[t].T @ vxx @ A[t]
            if t > 0:  # x_0 is given: no cost on it
                e, J = self.cost.jacobian(*self.sim.qv(states[t]), step + t - 1)
                qx, qxx = qx + J.T @ (w * e), qxx + J.T @ (w[:, None] * J)
            qu = c * actions[t] + B[t].T @ vx
            quu = (c + mu) * eye + B[t].T @ vxx @ B[t]
            qux = B[t].T @ vxx @ A[t]
            try:
                chol = cho_factor(quu, check_finite=False)
            except np.linalg.LinAlgError:
                return None
            gains = -cho_solve(chol, np.hstack([qu[:, None], qux]), check_finite=False)
            k[t], K[t] = gains[:, 0], gains[:, 1:]
            vx = qx + K[t].T @ quu @ k[t] + K[t].T @ qu + qux.T @ k[t]
            vxx = qxx + K[t].T @ quu @ K[t] + K[t].T @ qux + qux.T @ K[t]
            vxx = 0.5 * (vxx + vxx.T)
        return k, K

    def _forward(
        self, states: np.ndarray, actions: np.ndarray, k: np.ndarray, K: np.ndarray, alpha: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Closed-loop rollout of the updated policy. -> states (H + 1, nstate), actions (H, nu)"""
        model, data = self.model, self.data
        new_states, new_actions = np.empty_like(states), np.empty_like(actions)
        new_states[0] = states[0]
        for t in range(actions.shape[0]):
            dx = self.tangent(new_states[t], states[t])
            new_actions[t] = np.clip(actions[t] + alpha * k[t] + K[t] @ dx, self.low, self.high)
            mujoco.mj_setState(model, data, new_states[t], FULLPHYSICS)
            data.ctrl[:] = new_actions[t]
            mujoco.mj_step(model, data, nstep=self.frame_skip)
            mujoco.mj_getState(model, data, new_states[t + 1], FULLPHYSICS)
        return new_states, new_actions

    def plan(self, state: np.ndarray, actions: np.ndarray, step: int = 0) -> ILQRResult:
        """Improve actions (H, nu) from FULLPHYSICS `state` (nstate,) at episode `step`."""
        with self.blas.limit(limits=1, user_api="blas"):
            return self._plan(state, actions, step)

    def _plan(self, state: np.ndarray, actions: np.ndarray, step: int) -> ILQRResult:
        s = self.settings
        actions = np.clip(np.asarray(actions, float), self.low, self.high)
        states = np.concatenate([state[None], self.sim(state[None], actions[None])[0]])
        cost = initial = self.total_cost(states, actions, step)
        mu, accepted, derivatives = s.regularization, 0, None
        for _ in range(s.iterations):
            if derivatives is None:  # the trajectory moved (or the first iteration)
                derivatives = self.derivatives(states, actions)
            A, B = derivatives
            gains = self._backward(states, actions, A, B, step, mu)
            while gains is None:
                mu *= 10.0
                gains = self._backward(states, actions, A, B, step, mu)
            for alpha in s.line_search:
                trial_states, trial_actions = self._forward(states, actions, *gains, alpha)
                trial = self.total_cost(trial_states, trial_actions, step)
                if trial < cost:
                    states, actions, cost = trial_states, trial_actions, trial
                    accepted += 1
                    if not s.reuse_derivatives:
                        derivatives = None
                    mu = max(mu / 3.0, 1e-8)
                    break
            else:
                mu *= 10.0
        return ILQRResult(actions=actions, cost=cost, initial_cost=initial, accepted=accepted)


@dataclass
class ILQRStart:
    """Where an iLQR plan starts: MuJoCo's FULLPHYSICS state (nstate,) at episode `step`."""

    state: np.ndarray
    step: int


class ILQRStarts(ObjectiveFactory):
    """What `PlannerPolicy` asks of its objective factory, for `ILQRPlanner`: the state and
    episode step a plan starts from (the cost is the planner's `ResidualCost`)."""

    time_indexed = True  # the tracking residuals follow the reference in time

    def __init__(self, ilqr: MujocoILQR) -> None:
        self.ilqr = ilqr

    def __call__(self, q: Tensor, qd: Tensor, step: int = 0) -> ILQRStart:
        as_np = lambda x: x.detach().to("cpu", torch.float64).numpy()  # noqa: E731
        return ILQRStart(self.ilqr.full_state(as_np(q), as_np(qd)), step)

    def close(self) -> None:
        self.ilqr.close()


class ILQRPlanner:
    """`MujocoILQR` as a planner of `PlannerPolicy`: plans (H, nu) in float64 on the CPU,
    the first one from zeros, each next from the previous one shifted by the steps executed
    since (its last action repeated). Nothing else is carried between plans."""

    def __init__(self, ilqr: MujocoILQR) -> None:
        self.ilqr = ilqr
        self.horizon = ilqr.settings.horizon

    def initial_mean(self, device: torch.device | str | None = None) -> Tensor:
        """Zeros (H, nu)."""
        return torch.zeros(self.horizon, self.ilqr.nu, dtype=torch.float64, device=device)

    def shift(self, plan: Tensor, steps: int) -> Tensor:
        """plan[steps:] followed by its last action `steps` times. (H, nu)"""
        return torch.cat([plan[steps:], plan[-1:].expand(steps, -1)])

    def warm_start(self, carried: dict[str, Tensor], steps: int) -> dict[str, Any]:
        return {}

    def carry(self, result: ILQRResult) -> dict[str, Tensor]:
        return {}

    def plan(
        self, start: ILQRStart, init: Tensor, generator: torch.Generator | None = None
    ) -> ILQRResult:
        """Improve `init` (H, nu) from `start` (`ILQRStarts`); `generator` is unused."""
        result = self.ilqr.plan(start.state, init.cpu().numpy(), start.step)
        log.debug(
            "iLQR step %d: cost %.4g -> %.4g (%d of %d iterations accepted)", start.step,
            result.initial_cost, result.cost, result.accepted, self.ilqr.settings.iterations,
        )  # fmt: skip
        return result

    def close(self) -> None:
        self.ilqr.close()
