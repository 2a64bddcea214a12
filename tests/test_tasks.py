"""Tasks: closed-form kinematics against MuJoCo, reward shape and range, batching, seeding."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.systems.system import load_system
from mbrl_delan.tasks import AcrobotSwingup, ArmReach, CartpoleSwingup, PendulumSwingup, Task
from mbrl_delan.tasks.arm_reach import ARM2_LINK_LENGTHS, ARM3_LINK_LENGTHS

# (asset, task, MuJoCo site of each tip the task computes)
KINEMATICS = {
    "pendulum": (PendulumSwingup(), ("tip",)),
    "cartpole": (CartpoleSwingup(), ("tip",)),
    "acrobot": (AcrobotSwingup(), ("tip1", "tip2")),
    "arm2": (ArmReach(), ("tip1", "tip2")),
    "arm3": (ArmReach(link_lengths=ARM3_LINK_LENGTHS), ("tip1", "tip2", "tip3")),
}

TASKS: dict[str, Task] = {
    "pendulum": PendulumSwingup(),
    "cartpole": CartpoleSwingup(),
    "acrobot": AcrobotSwingup(),
    "arm_reach": ArmReach(),
}
SIZES = {"pendulum": (1, 1), "cartpole": (2, 1), "acrobot": (2, 1), "arm_reach": (2, 2)}  # nq, nu


def arm2_inverse_kinematics(target: tuple[float, float]) -> torch.Tensor:
    """Joint angles (2,) putting arm2's tip at target (x, z) (elbow one way)."""
    (l1, l2), (x, z) = ARM2_LINK_LENGTHS, target
    q2 = math.acos((x * x + z * z - l1 * l1 - l2 * l2) / (2 * l1 * l2))
    q1 = math.atan2(x, -z) - math.atan2(l2 * math.sin(q2), l1 + l2 * math.cos(q2))
    return torch.tensor([q1, q2], dtype=torch.float64)


GOALS = {  # a state with reward 1 (zero velocity and zero action)
    "pendulum": torch.tensor([math.pi], dtype=torch.float64),
    "cartpole": torch.tensor([0.0, -math.pi], dtype=torch.float64),
    "acrobot": torch.tensor([math.pi, 0.0], dtype=torch.float64),
    "arm_reach": arm2_inverse_kinematics(ArmReach().target),
}


@pytest.mark.parametrize("asset", sorted(KINEMATICS))
def test_tip_positions_match_mujoco_sites(asset: str) -> None:
    task, sites = KINEMATICS[asset]
    model = load_system(asset).mj_model()
    data = mujoco.MjData(model)
    q = np.random.default_rng(0).uniform(-2 * math.pi, 2 * math.pi, size=(20, model.nq))
    tips = task.tip_positions(torch.from_numpy(q))  # (20, n_sites, 2)
    assert tips.shape == (20, len(sites), 2)
    for i in range(len(q)):
        data.qpos[:] = q[i]
        mujoco.mj_kinematics(model, data)
        for k, site in enumerate(sites):
            xyz = data.site(site).xpos
            np.testing.assert_allclose(tips[i, k].numpy(), xyz[[0, 2]], atol=1e-9, rtol=0)
            assert abs(xyz[1]) < 1e-12  # planar: everything in the x-z plane


def random_batch(name: str, shape: tuple[int, ...], seed: int = 0) -> tuple[torch.Tensor, ...]:
    nq, nu = SIZES[name]
    gen = torch.Generator().manual_seed(seed)
    q = 4.0 * torch.randn(*shape, nq, generator=gen, dtype=torch.float64)
    qd = 3.0 * torch.randn(*shape, nq, generator=gen, dtype=torch.float64)
    action = 1.5 * torch.randn(*shape, nu, generator=gen, dtype=torch.float64)
    return q, qd, action


@pytest.mark.parametrize("name", sorted(TASKS))
def test_reward_is_one_at_goal_and_lower_elsewhere(name: str) -> None:
    task, goal = TASKS[name], GOALS[name]
    nq, nu = SIZES[name]
    rest, idle = torch.zeros(nq, dtype=torch.float64), torch.zeros(nu, dtype=torch.float64)
    assert task.reward(goal, rest, idle).item() == pytest.approx(1.0, abs=1e-12)
    q, qd, action = random_batch(name, (500,))
    reward = task.reward(q, qd, action)
    assert reward.shape == (500,)
    assert (reward >= 0).all() and (reward < 1).all()
    # moving, pushing or leaving the goal each costs reward
    assert task.reward(goal, rest + 0.5, idle) < 1
    assert task.reward(goal, rest, idle + 0.5) < 1
    assert task.reward(goal + 0.3, rest, idle) < 1
    # hanging down at rest is far from the goal
    assert task.reward(torch.zeros(nq, dtype=torch.float64), rest, idle) < 0.1


@pytest.mark.parametrize("name", sorted(TASKS))
def test_reward_has_gradient_away_from_goal(name: str) -> None:
    q, qd, action = random_batch(name, (64,), seed=1)
    q = (0.3 * q).requires_grad_(True)
    TASKS[name].reward(q, qd, action).sum().backward()
    assert torch.isfinite(q.grad).all()
    assert (q.grad.abs().sum(-1) > 0).float().mean() > 0.9


@pytest.mark.parametrize("name", sorted(TASKS))
def test_reward_batched_over_two_dims_equals_per_sample(name: str) -> None:
    task = TASKS[name]
    q, qd, action = random_batch(name, (3, 5), seed=2)
    batched = task.reward(q, qd, action)
    assert batched.shape == (3, 5)
    for i in range(3):
        for j in range(5):
            single = task.reward(q[i, j], qd[i, j], action[i, j])
            assert single.shape == ()
            torch.testing.assert_close(batched[i, j], single, atol=1e-14, rtol=0)
    terminated = task.terminated(q, qd)
    assert terminated.shape == (3, 5) and terminated.dtype == torch.bool
    # other float dtypes pass through
    assert task.reward(q.float(), qd.float(), action.float()).dtype == torch.float32


@pytest.mark.parametrize("name", sorted(TASKS))
def test_initial_states_reproducible_and_near_rest(name: str) -> None:
    task = TASKS[name]
    nq, _ = SIZES[name]
    a = task.initial_state((4, 3), torch.Generator().manual_seed(7))
    b = task.initial_state((4, 3), torch.Generator().manual_seed(7))
    c = task.initial_state((4, 3), torch.Generator().manual_seed(8))
    assert a.q.shape == (4, 3, nq) and a.qd.shape == (4, 3, nq) and a.q.dtype == torch.float64
    assert torch.equal(a.q, b.q) and torch.equal(a.qd, b.qd)
    assert not torch.equal(a.q, c.q)
    assert a.q.abs().max() < 0.5 and a.qd.abs().max() < 0.5  # hanging down, nearly at rest
    assert a.q.std() > 0  # but not all the same


def test_arm_reach_rejects_unreachable_target() -> None:
    with pytest.raises(ValueError, match="out of reach"):
        ArmReach(target=(2.0, 0.0))
