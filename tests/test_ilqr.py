"""The iLQR oracle: exact LQR on a linear system, MuJoCo-consistent derivatives, tracking."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mbrl_delan.envs.real import make_real_env
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.planners.ilqr import ILQRPlanner, ILQRSettings, ILQRStarts, MujocoILQR
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.planners.tracking_residual import TrackingResidual, tracking_ilqr_policy
from mbrl_delan.training.loop import run_episode
from tests.test_tracking import RUN_CLIP

# a 2 kg point mass on two slide joints, no gravity, damping or contacts, semi-implicit
# Euler: a linear system, x_{k+1} = A1 x_k + B1 u_k per physics step
POINT_MASS = """
<mujoco>
  <option timestep="0.05" integrator="Euler" gravity="0 0 0"/>
  <worldbody>
    <body>
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <geom type="sphere" size="0.1" mass="2" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="x" ctrlrange="-1000 1000"/>
    <motor joint="y" ctrlrange="-1000 1000"/>
  </actuator>
</mujoco>
"""


class Quadratic:
    """e = x = (q, qd), weights (2 nv,): a regulator to the origin."""

    def __init__(self, weights: np.ndarray) -> None:
        self.weights = weights

    def residual(self, q: np.ndarray, qd: np.ndarray, step: int) -> np.ndarray:
        return np.concatenate([q, qd])

    def jacobian(self, q: np.ndarray, qd: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        return self.residual(q, qd, step), np.eye(q.size + qd.size)


def lqr_first_action(
    A: np.ndarray, B: np.ndarray, Q: np.ndarray, c: float, horizon: int, x0: np.ndarray
) -> np.ndarray:
    """Riccati recursion for sum_{t=1..H} x^T Q x / 2 + sum_{t<H} c |u|^2 / 2. -> u_0"""
    P = Q
    for t in range(horizon - 1, -1, -1):
        K = np.linalg.solve(c * np.eye(B.shape[1]) + B.T @ P @ B, B.T @ P @ A)
        P = (Q if t > 0 else 0 * Q) + A.T @ P @ (A - B @ K)
    return -K @ x0


@pytest.mark.parametrize("frame_skip", [1, 3])
def test_ilqr_first_action_is_the_lqr_action_on_a_linear_system(frame_skip):
    model = mujoco.MjModel.from_xml_string(POINT_MASS)
    h, mass, horizon, c = model.opt.timestep, 2.0, 8, 0.01
    A1 = np.block([[np.eye(2), h * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    B1 = np.vstack([h * h / mass * np.eye(2), h / mass * np.eye(2)])
    A, B = np.eye(4), np.zeros((4, 2))
    for _ in range(frame_skip):
        A, B = A1 @ A, A1 @ B + B1
    Q = np.diag([10.0, 4.0, 1.0, 0.5])
    x0 = np.array([1.0, -0.5, 0.3, 0.8])
    expected = lqr_first_action(A, B, Q, c, horizon, x0)

    settings = ILQRSettings(horizon=horizon, iterations=1, control_weight=c, regularization=1e-12)
    ilqr = MujocoILQR(
        model, frame_skip, model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1],
        Quadratic(np.diag(Q).copy()), settings,
    )  # fmt: skip
    result = ilqr.plan(ilqr.full_state(x0[:2], x0[2:]), np.zeros((horizon, 2)))
    np.testing.assert_allclose(result.actions[0], expected, rtol=1e-5, atol=1e-6)
    assert result.accepted == 1 and result.cost < result.initial_cost
    Ad, Bd = ilqr.derivatives(ilqr.full_state(x0[:2], x0[2:])[None], np.zeros((1, 2)))
    np.testing.assert_allclose(Ad[0], A, atol=1e-6)
    np.testing.assert_allclose(Bd[0], B, atol=1e-7)


def test_iterations_without_a_step_reuse_the_derivatives():
    """At rest at the regulator's optimum (x 0, u 0, cost 0) no line search finds a lower
    cost: the trajectory stays, so all iterations share the first one's derivatives. Away
    from it, an accepted step moves the trajectory and the next iteration takes new ones."""
    model = mujoco.MjModel.from_xml_string(POINT_MASS)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    settings = ILQRSettings(horizon=6, iterations=4, control_weight=0.01)
    ilqr = MujocoILQR(model, 1, low, high, Quadratic(np.ones(4)), settings)
    calls = []
    derivatives = ilqr.derivatives
    ilqr.derivatives = lambda *args: calls.append(1) or derivatives(*args)
    rest = ilqr.plan(ilqr.full_state(np.zeros(2), np.zeros(2)), np.zeros((6, 2)))
    assert rest.accepted == 0 and rest.cost == rest.initial_cost == 0.0
    assert len(calls) == 1
    calls.clear()
    moved = ilqr.plan(ilqr.full_state(np.array([1.0, -0.5]), np.zeros(2)), np.zeros((6, 2)))
    assert moved.accepted >= 1 and moved.cost < moved.initial_cost
    assert 2 <= len(calls) <= 1 + moved.accepted


def test_reused_derivatives_are_taken_once_per_plan_and_exact_on_a_linear_system():
    """`reuse_derivatives`: one A, B per plan however many iterations move the trajectory. On
    a linear system A, B are the same everywhere, so the plan is the one of fresh derivatives
    (Gauss-Newton on a quadratic cost: the first iteration already solves it)."""
    model = mujoco.MjModel.from_xml_string(POINT_MASS)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    start = np.array([1.0, -0.5]), np.array([0.3, 0.8])
    plans = {}
    for reuse in (False, True):
        settings = ILQRSettings(
            horizon=6, iterations=3, control_weight=0.01, reuse_derivatives=reuse
        )
        ilqr = MujocoILQR(model, 2, low, high, Quadratic(np.ones(4)), settings)
        calls = []
        derivatives = ilqr.derivatives
        ilqr.derivatives = lambda *args, d=derivatives, c=calls: c.append(1) or d(*args)
        plans[reuse] = ilqr.plan(ilqr.full_state(*start), np.zeros((6, 2)))
        assert plans[reuse].accepted >= 1
        assert len(calls) == (1 if reuse else 1 + min(plans[reuse].accepted, 2))
    np.testing.assert_allclose(plans[True].actions, plans[False].actions, rtol=1e-6, atol=1e-6)
    assert plans[True].cost == pytest.approx(plans[False].cost, rel=1e-9)


def chained_transition(model, state, ctrl, frame_skip):
    """A, B of frame_skip physics steps chained from MuJoCo's own mjd_transitionFD."""
    data = mujoco.MjData(model)
    n = 2 * model.nv
    A, B = np.eye(n), np.zeros((n, model.nu))
    mujoco.mj_setState(model, data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    data.ctrl[:] = ctrl
    for _ in range(frame_skip):
        Ai, Bi = np.zeros((n, n)), np.zeros((n, model.nu))
        mujoco.mjd_transitionFD(model, data, 1e-6, True, Ai, Bi, None, None)
        A, B = Ai @ A, Ai @ B + Bi
        mujoco.mj_step(model, data)
    return A, B


@pytest.mark.parametrize(
    ("env", "lift"), [("pendulum", 0.0), ("humanoid_stand", 5.0)]
)  # the humanoid in the air: a free joint, no contacts
def test_derivatives_match_mujocos_transition_matrices(env, lift):
    system = make_env_parts(env).system
    model = system.mj_model()
    if model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:  # mjd_transitionFD has no RK4
        model.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    q = data.qpos.copy()
    if lift:
        q[2] += lift
        q[7:] += rng.uniform(-0.2, 0.2, model.nq - 7)
    else:
        q += rng.uniform(-1, 1, model.nq)
    qd = rng.uniform(-0.5, 0.5, model.nv)
    low, high = system.ctrl_low.numpy(), system.ctrl_high.numpy()
    u = rng.uniform(0.5 * low, 0.5 * high)
    ilqr = MujocoILQR(model, 2, low, high, Quadratic(np.ones(2 * model.nv)), nthread=2)
    state = ilqr.full_state(q, qd)
    A, B = ilqr.derivatives(state[None], u[None])
    A_ref, B_ref = chained_transition(model, state, u, 2)
    np.testing.assert_allclose(A[0], A_ref, atol=2e-5 * max(1.0, np.abs(A_ref).max()))
    np.testing.assert_allclose(B[0], B_ref, atol=2e-5 * max(1e-3, np.abs(B_ref).max()))


@pytest.fixture(scope="module")
def track():
    return make_env_parts("cmu_track", task_options=RUN_CLIP)


def test_tracking_residual_is_zero_on_the_reference_and_its_jacobian_is_exact(track):
    model = track.system.mj_model()
    cost = TrackingResidual(model, track.task, point_weight=30.0, point_velocity_weight=1.0)
    j, nv, n_vel = 5, model.nv, 3 * len(cost.moving)
    assert n_vel == 48  # the 16 body points
    ref_q, ref_qd = cost.ref_q[j], cost.ref_qd[j]
    np.testing.assert_allclose(cost.residual(ref_q, ref_qd, j - 1), 0.0, atol=1e-12)
    rng = np.random.default_rng(1)
    q = ref_q.copy()
    mujoco.mj_integratePos(model, q, rng.uniform(-0.2, 0.2, nv), 1.0)
    qd = ref_qd + rng.uniform(-1, 1, nv)
    e, J = cost.jacobian(q, qd, j - 1)
    eps = 1e-6
    fd = np.empty_like(J)
    for i in range(2 * nv):
        dq, dqd = np.zeros(nv), np.zeros(nv)
        (dq if i < nv else dqd)[i % nv] = eps
        qp = q.copy()
        mujoco.mj_integratePos(model, qp, dq, 1.0)
        fd[:, i] = (cost.residual(qp, qd + dqd, j - 1) - e) / eps
    # all rows but the root rotation's (a Gauss-Newton approximation) and the body velocities'
    exact = np.r_[3 : e.size - n_vel]
    np.testing.assert_allclose(J[exact], fd[exact], atol=1e-4)
    # a body velocity J_b(q) qd: exact along qd; its change with q is left out (zero columns)
    np.testing.assert_allclose(J[e.size - n_vel :, nv:], fd[e.size - n_vel :, nv:], atol=1e-4)
    assert not J[e.size - n_vel :, :nv].any() and np.abs(fd[e.size - n_vel :, :nv]).max() > 0.1
    assert cost.weights.shape == e.shape and cost.weights.min() >= 0
    np.testing.assert_array_equal(cost.weights[e.size - n_vel :], 1.0)


def test_tracking_body_velocities_are_mujocos(track):
    """The reference's body velocities J_b(q_ref) qd_ref equal MuJoCo's own (`mj_objectVelocity`
    of the body frame, world-aligned linear part)."""
    model = track.system.mj_model()
    cost = TrackingResidual(model, track.task, point_weight=0.0, point_velocity_weight=1.0)
    data = mujoco.MjData(model)
    j = 7
    data.qpos[:], data.qvel[:] = cost.ref_q[j], cost.ref_qd[j]
    mujoco.mj_forward(model, data)
    res = np.zeros(6)
    for body, v in zip(cost.moving, cost.ref_velocities[j], strict=True):
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, body, res, 0)
        np.testing.assert_allclose(v, res[3:], atol=1e-9)
    assert np.abs(cost.ref_velocities[j]).max() > 0.1  # the clip moves


def test_ilqr_policy_tracks_better_than_zero_torques_on_the_test_clip(track):
    steps = 4
    model, system = track.system.mj_model(), track.system
    cost = TrackingResidual(model, track.task, point_weight=30.0)
    ilqr = MujocoILQR(
        model, system.frame_skip, system.ctrl_low.numpy(), system.ctrl_high.numpy(), cost,
        ILQRSettings(horizon=3, iterations=1), nthread=2,
    )  # fmt: skip
    policy = PlannerPolicy(ILQRPlanner(ilqr), ILQRStarts(ilqr))
    env = make_real_env("cmu_track", seed=0, episode_len=steps, task_options=RUN_CLIP)
    rollout = run_episode(env, policy, seed=0, max_steps=steps)
    assert policy.last_result.cost <= policy.last_result.initial_cost
    env_zero = make_real_env("cmu_track", seed=0, episode_len=steps, task_options=RUN_CLIP)
    zero = env_zero.rollout(steps, policy=lambda td: td.set("action", torch.zeros(system.nu)))
    ilqr_return = float(rollout["next", "reward"].sum())
    assert rollout.shape[0] == steps
    assert ilqr_return > float(zero["next", "reward"].sum()) + 0.05


def test_ilqr_policy_names_bad_input():
    pendulum = make_env_parts("pendulum")
    with pytest.raises(ValueError, match="needs a motion-tracking task"):
        tracking_ilqr_policy(pendulum.system, pendulum.task)
    model = mujoco.MjModel.from_xml_string(POINT_MASS)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    ilqr = MujocoILQR(model, 1, low, high, Quadratic(np.ones(4)))
    policy = PlannerPolicy(ILQRPlanner(ilqr), ILQRStarts(ilqr))
    unbatched = TensorDict({"q": torch.zeros(3, 2), "qd": torch.zeros(3, 2)}, batch_size=[])
    with pytest.raises(ValueError, match="PlannerPolicy needs unbatched q"):
        policy(unbatched)  # a batch of states must be the tensordict's batch (one plan each)
    with pytest.raises(ValueError, match="horizon and iterations must be >= 1"):
        ILQRSettings(horizon=0)
