"""The humanoid's balance cost (`BalanceCost`) against MuJoCo and worked values."""

import math
from dataclasses import replace

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.objectives.mujoco import MujocoObjectiveFactory, PlanPhysics
from mbrl_delan.planners.predictive import PredictiveSampling
from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.tasks.balance import BalanceCost, BalanceWeights
from mbrl_delan.tasks.humanoid import HUMANOID_V5_BODY, HumanoidTask


@pytest.fixture(scope="module")
def v5() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))


@pytest.fixture(scope="module")
def cost(v5) -> BalanceCost:
    return BalanceCost(v5, HumanoidTask(v5, HUMANOID_V5_BODY, ctrl_max=0.4))


@pytest.fixture(scope="module")
def walk(v5) -> BalanceCost:
    return BalanceCost(v5, HumanoidTask(v5, HUMANOID_V5_BODY, speed=1.0, ctrl_max=0.4))


def rest(model: mujoco.MjModel) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return torch.from_numpy(model.qpos0.copy()), torch.zeros(model.nv), torch.zeros(model.nu)


def test_centre_of_mass_and_its_velocity_equal_mujocos(v5, cost) -> None:
    data, rng = mujoco.MjData(v5), np.random.default_rng(0)
    for _ in range(3):
        data.qpos[:] = v5.qpos0 + 0.3 * rng.standard_normal(v5.nq)
        data.qpos[3:7] /= np.linalg.norm(data.qpos[3:7])
        data.qvel[:] = rng.standard_normal(v5.nv)
        mujoco.mj_forward(v5, data)
        mujoco.mj_subtreeVel(v5, data)
        com = cost.centre_of_mass(torch.tensor(data.qpos), torch.tensor(data.qvel))
        np.testing.assert_allclose(com.position.numpy(), data.subtree_com[0], atol=1e-12)
        np.testing.assert_allclose(com.velocity.numpy(), data.subtree_linvel[0], atol=1e-12)
        feet = cost.body_state(torch.tensor(data.qpos), torch.tensor(data.qvel)).feet_velocity
        velocity = np.zeros(6)
        expected = np.zeros(3)
        for foot in cost.feet:  # each foot's origin: MuJoCo's (angular, linear) of the xbody
            mujoco.mj_objectVelocity(v5, data, mujoco.mjtObj.mjOBJ_XBODY, foot, velocity, 0)
            expected += velocity[3:] / len(cost.feet)
        np.testing.assert_allclose(feet.numpy(), expected, atol=1e-12)


def test_capture_point_of_a_body_moving_at_a_known_velocity(v5, cost) -> None:
    """Every body translating at 0.5 m/s along x: the capture point leads the centre of mass
    by 0.5 sqrt(z / g), z its height above the ground given."""
    q, qd, _ = rest(v5)
    qd[0] = 0.5
    com = cost.centre_of_mass(q, qd)
    torch.testing.assert_close(com.velocity, torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    ground = torch.tensor(0.1, dtype=torch.float64)
    lead = 0.5 * math.sqrt((float(com.position[2]) - 0.1) / 9.81)
    expected = com.position[:2] + torch.tensor([lead, 0.0], dtype=torch.float64)
    torch.testing.assert_close(cost.capture_point(com, ground), expected)


def test_upright_and_still_is_the_minimum_and_a_tilted_pose_costs_more(v5, cost) -> None:
    q, qd, a = rest(v5)
    terms = cost.terms(q, qd, a)
    for name in ("height", "upright", "com_velocity", "joint_velocity", "posture", "control"):
        assert terms[name].item() == pytest.approx(0.0, abs=1e-12), name
    assert terms["balance"].item() < 0.02**2  # the standing pose's centre of mass: 1.7 cm off
    tilted = q.clone()  # the whole body turned 20 degrees about y, about its root
    tilted[3:7] = torch.tensor([math.cos(math.radians(10)), 0.0, math.sin(math.radians(10)), 0])
    tilted_terms = cost.terms(tilted, qd, a)
    for name in ("height", "upright", "balance"):
        assert tilted_terms[name] > terms[name] + 1e-3, name
    assert tilted_terms["upright"].item() == pytest.approx(1 - math.cos(math.radians(20)))
    moving, pushed = qd.clone(), a + 0.4
    moving[6:] = 2.0
    assert cost.terms(q, moving, pushed)["joint_velocity"].item() == pytest.approx(4.0)
    assert cost.terms(q, moving, pushed)["control"].item() == pytest.approx(1.0)
    assert cost.reward(tilted, qd, a) < cost.reward(q, qd, a) <= 0


def test_walking_velocity_is_measured_against_the_speed(v5, walk) -> None:
    q, qd, a = rest(v5)
    assert walk.terms(q, qd, a)["com_velocity"].item() == pytest.approx(1.0)
    qd[0] = 1.0  # every body at 1 m/s: the feet go along with the centre of mass
    terms = walk.terms(q, qd, a)
    assert terms["com_velocity"].item() == pytest.approx(0.0, abs=1e-12)
    assert terms["feet_velocity"].item() == pytest.approx(0.0, abs=1e-12)
    qd[:] = 0.0
    qd[11] = 1.0  # the right hip's flexion at 1 rad/s: the foot swings, the body barely moves
    assert walk.terms(q, qd, a)["feet_velocity"].item() > 0.01


def test_a_planning_speed_replaces_the_tasks_and_only_on_a_walk(v5, cost, walk) -> None:
    q, qd, a = rest(v5)
    faster = BalanceCost(v5, walk.task, speed=1.25)
    qd[0] = 1.0  # moving at the task's speed: short of the planning speed by 0.25 m/s
    assert walk.terms(q, qd, a)["com_velocity"].item() == pytest.approx(0.0, abs=1e-12)
    assert faster.terms(q, qd, a)["com_velocity"].item() == pytest.approx(0.25**2)
    for task, speed in ((cost.task, 1.0), (walk.task, -1.0), (walk.task, math.nan)):
        with pytest.raises(ValueError, match="planning speed"):
            BalanceCost(v5, task, speed=speed)


def test_heading_is_the_torso_facing_away_from_x(v5, walk) -> None:
    q, qd, a = rest(v5)
    assert walk.terms(q, qd, a)["heading"].item() == pytest.approx(0.0, abs=1e-12)
    for degrees, expected in ((90, 1.0), (180, 2.0)):
        turned = q.clone()  # the whole body turned about z: still upright
        half = math.radians(degrees / 2)
        turned[3:7] = torch.tensor([math.cos(half), 0.0, 0.0, math.sin(half)])
        terms = walk.terms(turned, qd, a)
        assert terms["heading"].item() == pytest.approx(expected)
        assert terms["upright"].item() == pytest.approx(0.0, abs=1e-12)


def test_the_support_is_the_midpoint_or_the_segment_between_the_feet(v5, cost, walk) -> None:
    """Feet at y = +-0.1: standing (span 0) supports the midpoint only; walking (span 1) the
    whole segment, so a capture point between the feet costs nothing and one beyond a foot
    is measured from that foot."""
    feet = torch.tensor([[0.0, -0.1, 0.0], [0.0, 0.1, 0.0]], dtype=torch.float64)
    inside = torch.tensor([0.0, 0.05], dtype=torch.float64)
    beyond = torch.tensor([0.03, 0.3], dtype=torch.float64)
    middle = torch.zeros(2, dtype=torch.float64)
    torch.testing.assert_close(cost.support_point(feet, inside), middle)
    torch.testing.assert_close(walk.support_point(feet, inside), inside)
    torch.testing.assert_close(walk.support_point(feet, beyond),
                               torch.tensor([0.0, 0.1], dtype=torch.float64))  # fmt: skip
    with pytest.raises(ValueError, match="support_span"):
        BalanceCost(v5, walk.task, support_span=1.5)


def test_bad_weights_and_a_model_without_the_feet_are_refused(v5) -> None:
    with pytest.raises(ValueError, match="balance weight height"):
        BalanceWeights(height=-1.0)
    task = HumanoidTask(v5, replace(HUMANOID_V5_BODY, feet=("no_foot",)))
    with pytest.raises(ValueError, match="foot bodies"):
        BalanceCost(v5, task)


def test_a_sampling_planner_on_the_cost_finds_the_worked_optimum(v5, cost) -> None:
    """States that do not depend on the actions (the standing pose): only the control term
    differs between plans, so the best plan is no action; predictive sampling of one held
    action from 0.2 moves toward 0 and never away."""
    q, qd, _ = rest(v5)
    horizon, nu = 5, v5.nu

    def objective(actions: torch.Tensor) -> torch.Tensor:  # (N, H, nu) -> (N,)
        n = actions.shape[0]
        states = q.expand(n, horizon, -1), qd.expand(n, horizon, -1)
        return cost.reward(*states, actions.double()).sum(-1)

    bound = torch.full((nu,), 0.4)
    planner = PredictiveSampling(horizon, -bound, bound, num_samples=64, iterations=40,
                                 noise_std=0.05, dtype=torch.float64, knots=1,
                                 interpolation="zero")  # fmt: skip
    start = torch.full((horizon, nu), 0.2, dtype=torch.float64)
    plan = planner.plan(objective, init_mean=start,
                        generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert plan.mean.abs().mean() < 0.05
    assert torch.all(plan.iteration_best.diff() >= 0)
    assert objective(plan.mean.unsqueeze(0)) > objective(start.unsqueeze(0))


@pytest.mark.parametrize("env", ["humanoid_stand", "humanoid_walk"])
def test_the_oracle_scores_from_sensors_what_torch_scores_from_the_states(v5, env) -> None:
    """The planning model's sensors give the body state of each reached state (one step
    later in MuJoCo's own order: the rollout takes one more step for the last one)."""
    parts = make_env_parts(env)
    cost = BalanceCost(v5, parts.task)
    factory = MujocoObjectiveFactory(parts.system, cost, nthread=1, physics=PlanPhysics(2))
    assert factory.sensed and factory.model.nsensordata == cost.sensor_size
    start = parts.task.initial_state((), torch.Generator().manual_seed(0))
    actions = 0.3 * torch.randn(4, 6, v5.nu, generator=torch.Generator().manual_seed(1))
    result = factory.rollout(factory.initial_state(start.q, start.qd), actions.double())
    q, qd = result.states.q, result.states.qd
    sensed, computed = cost.sensed_state(result.sensors), cost.body_state(q, qd)
    for name in ("head_z", "up_z", "forward_x", "feet", "feet_velocity"):
        torch.testing.assert_close(getattr(sensed, name), getattr(computed, name))
    torch.testing.assert_close(sensed.com.velocity, computed.com.velocity)
    torch.testing.assert_close(cost.sensed_reward(result.sensors, q, qd, result.actions),
                               cost.reward(q, qd, result.actions))  # fmt: skip
    factory.close()
