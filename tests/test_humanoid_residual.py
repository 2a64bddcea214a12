"""The humanoid residuals of the iLQR oracle: values at the standing pose, Jacobians against
finite differences in MuJoCo's tangent space, and a plan that lowers the cost."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.objectives.mujoco import PlanPhysics
from mbrl_delan.planners.humanoid_residual import HUMANOID_ILQR, HumanoidResidual
from mbrl_delan.planners.ilqr import MujocoILQR


@pytest.fixture(scope="module", params=["humanoid_stand", "humanoid_walk"])
def parts(request):
    return make_env_parts(request.param, None, 10)


def _cost(parts) -> HumanoidResidual:
    return HumanoidResidual(parts.system.mj_model(), parts.task)


def test_standing_still_at_qpos0_leaves_only_balance_and_the_speed(parts) -> None:
    cost = _cost(parts)
    nv = cost.model.nv
    e = cost.residual(cost.qpos0, np.zeros(nv), 0)
    assert e.shape == cost.weights.shape == (7 + 2 * (nv - 6),)
    np.testing.assert_allclose(e[:3], 0.0, atol=1e-12)  # head height and upright
    speed = parts.task.speed or 0.0
    np.testing.assert_allclose(e[3:5], [-speed, 0.0], atol=1e-12)
    np.testing.assert_allclose(e[7:], 0.0, atol=1e-12)  # posture, joint velocities
    assert np.abs(e[5:7]).max() < 0.05  # the centre of mass is above the feet (m)


def test_jacobian_matches_finite_differences_in_the_tangent_space(parts) -> None:
    cost, rng = _cost(parts), np.random.default_rng(0)
    model, nv = cost.model, cost.model.nv
    q = cost.qpos0.copy()
    mujoco.mj_integratePos(model, q, 0.2 * rng.standard_normal(nv), 1.0)
    qd, eps = rng.standard_normal(nv), 1e-6
    # q part at rest (the velocity residuals' change with q is left out by design), qd part
    # anywhere: both are then exact
    e0, J = cost.jacobian(q, np.zeros(nv), 0)
    fd = np.empty((e0.size, nv))
    for i in range(nv):
        step, qi = np.zeros(nv), q.copy()
        step[i] = eps
        mujoco.mj_integratePos(model, qi, step, 1.0)
        fd[:, i] = (cost.residual(qi, np.zeros(nv), 0) - e0) / eps
    np.testing.assert_allclose(J[:, :nv], fd, atol=2e-5)
    e1, J1 = cost.jacobian(q, qd, 0)
    fd_v = np.stack(
        [(cost.residual(q, qd + eps * np.eye(nv)[i], 0) - e1) / eps for i in range(nv)], axis=1
    )
    np.testing.assert_allclose(J1[:, nv:], fd_v, atol=2e-5)


def test_one_plan_from_rest_lowers_the_cost(parts) -> None:
    model, substeps = PlanPhysics(2, "euler").model(parts.system)
    system = parts.system
    ilqr = MujocoILQR(
        model, substeps, system.ctrl_low.numpy(), system.ctrl_high.numpy(),
        HumanoidResidual(model, parts.task), HUMANOID_ILQR,
    )  # fmt: skip
    try:
        state = ilqr.full_state(model.qpos0, np.zeros(model.nv))
        result = ilqr.plan(state, np.zeros((HUMANOID_ILQR.horizon, model.nu)))
    finally:
        ilqr.close()
    assert result.accepted >= 1 and result.cost < result.initial_cost
    assert np.all(np.abs(result.actions) <= system.ctrl_high.numpy() + 1e-12)


def test_a_task_without_feet_is_refused() -> None:
    from dataclasses import replace

    parts = make_env_parts("humanoid_stand", None, 10)
    parts.task.body = replace(parts.task.body, feet=("left_hoof",))
    with pytest.raises(ValueError, match="foot bodies"):
        HumanoidResidual(parts.system.mj_model(), parts.task)
