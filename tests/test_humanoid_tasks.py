"""Humanoid stand and walk rewards against worked-out values."""

import math

import mujoco
import pytest
import torch

from mbrl_delan.systems.external import humanoid_cmu_xml, humanoid_v5_xml
from mbrl_delan.tasks.humanoid import (
    HUMANOID_CMU_BODY,
    HUMANOID_V5_BODY,
    HumanoidTask,
    tolerance_below,
)


@pytest.fixture(scope="module")
def v5() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))


def rest(model: mujoco.MjModel) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return torch.from_numpy(model.qpos0.copy()), torch.zeros(model.nv), torch.zeros(model.nu)


def test_tolerance_is_one_above_and_a_tenth_one_margin_below() -> None:
    x = torch.tensor([2.0, 1.0, 0.5, 0.0], dtype=torch.float64)
    expected = torch.tensor([1.0, 1.0, 0.1**0.25, 0.1], dtype=torch.float64)
    torch.testing.assert_close(tolerance_below(x, lower=1.0, margin=1.0), expected)


def test_standing_at_rest_scores_one(v5) -> None:
    task = HumanoidTask(v5, HUMANOID_V5_BODY, ctrl_max=0.4)
    q, qd, a = rest(v5)
    assert task.head_height(q).item() == pytest.approx(1.4 + 0.19)  # root 1.4 m, head +0.19 m
    assert task.upright(q).item() == pytest.approx(1.0)
    assert task.reward(q, qd, a).item() == pytest.approx(1.0)
    assert not task.terminated(q, qd)


def test_lying_on_the_back(v5) -> None:
    """Root at 0.1 m, rotated 90 degrees about y: head at 0.1 m, torso up axis horizontal."""
    task = HumanoidTask(v5, HUMANOID_V5_BODY, ctrl_max=0.4)
    q, qd, a = rest(v5)
    q[2] = 0.1
    q[3:7] = torch.tensor([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0])
    assert task.head_height(q).item() == pytest.approx(0.1, abs=1e-12)
    assert task.upright(q).item() == pytest.approx(0.0, abs=1e-12)
    standing = 0.1 ** (((1.4 - 0.1) / 0.35) ** 2)
    upright = (1 + 0.1 ** ((0.9 / 1.9) ** 2)) / 2
    assert task.reward(q, qd, a).item() == pytest.approx(standing * upright)
    assert task.terminated(q, qd)  # head below 0.7 m


def test_control_and_velocity_factors(v5) -> None:
    stand = HumanoidTask(v5, HUMANOID_V5_BODY, ctrl_max=0.4)
    walk = HumanoidTask(v5, HUMANOID_V5_BODY, speed=1.0, ctrl_max=0.4, name="humanoid_walk")
    q, qd, a = rest(v5)
    full = torch.full_like(a, 0.4)  # every actuator at its limit
    assert stand.reward(q, qd, full).item() == pytest.approx((4 + math.exp(-1)) / 5)
    qd[0] = 2.0  # 2 m/s along x
    assert stand.reward(q, qd, a).item() == pytest.approx((0.1 + 1.0) / 2)
    assert walk.reward(q, qd, a).item() == pytest.approx(1.0)
    qd[0] = 0.5
    assert walk.reward(q, qd, a).item() == pytest.approx((1 + 5 * 0.5) / 6)


def test_batched_and_cmu_humanoid_stands_at_qpos0() -> None:
    cmu = mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))
    task = HumanoidTask(cmu, HUMANOID_CMU_BODY, stand_height=1.4)
    q, qd, a = rest(cmu)
    assert task.upright(q).item() == pytest.approx(1.0)  # body frames are y up
    assert task.head_height(q).item() > 1.4
    batch = task.reward(q.expand(3, 4, -1), qd.expand(3, 4, -1), a.expand(3, 4, -1))
    assert batch.shape == (3, 4)
    torch.testing.assert_close(batch, torch.ones(3, 4, dtype=torch.float64))


def test_initial_state_is_near_qpos0_with_a_unit_root_quaternion(v5) -> None:
    task = HumanoidTask(v5, HUMANOID_V5_BODY)
    state = task.initial_state((16,), torch.Generator().manual_seed(0))
    q0 = torch.from_numpy(v5.qpos0.copy())
    assert state.q.shape == (16, v5.nq) and state.qd.shape == (16, v5.nv)
    torch.testing.assert_close(state.q[:, 3:7].norm(dim=-1), torch.ones(16, dtype=torch.float64))
    assert (state.q - q0).abs().max() <= 0.011 and state.qd.abs().max() <= 0.01
    assert not task.terminated(state.q, state.qd).any()


def test_bad_arguments_name_the_problem(v5) -> None:
    with pytest.raises(ValueError, match="speed"):
        HumanoidTask(v5, HUMANOID_V5_BODY, speed=0.0)
    pendulum = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint type='hinge'/><geom size='.1'/></body></worldbody>"
        "</mujoco>"
    )
    with pytest.raises(ValueError, match="free root joint"):
        HumanoidTask(pendulum, HUMANOID_V5_BODY)
