"""Time-indexed tasks: the episode step reaches every reward, and cmu_track's terms."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch import Tensor
from torchrl.envs import StepCounter, TransformedEnv

from mbrl_delan import keys
from mbrl_delan.conf.checks import CONFIG_DIR
from mbrl_delan.envs.model_env import ModelEnv
from mbrl_delan.envs.real import env_parts_of, make_real_env
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.objectives.mujoco import mujoco_objective_factory
from mbrl_delan.planners import MPPIPlanner
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.systems.posarith import integrate_pos
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.tracking import (
    MotionTracking,
    TrackingScales,
    TrackingWeights,
    floor_clearance,
    ground_reference,
)
from tests.test_model_env import DoubleIntegrator

DATA = Path(__file__).parent / "data"
RUN_CLIP = {"clip": "09_06", "folders": [str(DATA)], "download": False}  # a 1.2 s run


class FollowRamp(Task):
    """Time-indexed: the action of step t should bring q to 0.1 (t + 1). r = -(q - 0.1 (t+1))^2."""

    name = "follow_ramp"
    episode_len = 20
    time_indexed = True

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        raise TypeError("time-indexed")

    def reward_at(self, q: Tensor, qd: Tensor, action: Tensor, step: Tensor) -> Tensor:
        return -(q[..., 0] - 0.1 * (step + 1)).square()

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        zeros = torch.zeros((*batch_shape, 1), dtype=torch.float64)
        return State(q=zeros, qd=zeros.clone())


@pytest.fixture(scope="module")
def track():
    return make_env_parts("cmu_track", task_options=RUN_CLIP)


# ---------------------------------------------------------------- the step reaches the reward


def test_model_objective_scores_each_step_at_its_episode_step() -> None:
    """By hand: with a = 0 the double integrator from q0 = 0, qd0 = 1 (DT = 0.1) reaches
    q_{t+1} = 0.1 (t + 1), the ramp exactly when its first action is step 0, and 0.3 behind it
    at every step when it is step 3."""
    factory = model_objective_factory(DoubleIntegrator(), FollowRamp())
    q0, qd0 = torch.zeros(1, dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    actions = torch.zeros(1, 4, 1, dtype=torch.float64)
    assert factory.time_indexed
    assert float(factory(q0, qd0, step=0)(actions)) == pytest.approx(0.0, abs=1e-12)
    assert float(factory(q0, qd0, step=3)(actions)) == pytest.approx(-4 * 0.3**2)


def test_policy_passes_the_episode_step_to_time_indexed_factories() -> None:
    steps: list[int] = []

    class Spy:
        time_indexed = True

        def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0):
            steps.append(step)
            return lambda actions: -actions.square().sum((-2, -1))

    planner = MPPIPlanner(horizon=3, action_low=[-1.0], action_high=[1.0], num_samples=8)
    policy = PlannerPolicy(planner, Spy(), replan_every=2)
    q, qd = torch.zeros(1), torch.zeros(1)
    for _ in range(5):
        policy.act(q, qd)
    assert steps == [0, 2, 4]
    policy.reset()
    policy.act(q, qd)
    assert steps[-1] == 0


def test_model_env_counts_the_step_a_time_indexed_task_reads() -> None:
    """The model env counts its steps (step_count), alone or under a StepCounter, and a
    time-indexed task scores step t against the reference at t; a start state without a step
    count is refused for such a task, naming the StepCounter to give its env."""
    system = make_env_parts("pendulum").system
    env = ModelEnv(DoubleIntegrator(), FollowRamp(), system)
    zero = lambda td: td.set(keys.ACTION, torch.zeros(1))  # noqa: E731
    for rollout_env in (env, TransformedEnv(env, StepCounter())):
        td = rollout_env.rollout(3, policy=zero)
        q = td[keys.NEXT_Q][..., 0]  # stays 0 (qd 0, a 0)
        expected = -(q - 0.1 * (torch.arange(3) + 1)).square()
        torch.testing.assert_close(td[keys.NEXT_REWARD].squeeze(-1), expected)
        assert td[keys.NEXT_STEP_COUNT].squeeze(-1).tolist() == [1, 2, 3]
    start = zero(env.reset().exclude(keys.STEP_COUNT))
    with pytest.raises(ValueError, match="StepCounter"):
        env.step(start)


def test_real_env_and_oracle_score_steps_of_the_reference(track) -> None:
    """The real env's reward of step t is reward_at(state, action, t); the oracle started at
    step s scores its H steps as s .. s+H-1 of a plain mj_step loop."""
    env = make_real_env("cmu_track", seed=0, episode_len=4, task_options=RUN_CLIP)
    task = env_parts_of(env).task
    g = torch.Generator().manual_seed(0)
    actions = 0.3 * torch.randn(4, track.system.nu, generator=g)
    env.set_seed(0)
    td = env.reset()
    start = State(q=td[keys.Q].double(), qd=td[keys.QD].double())
    for t in range(4):
        td = env.step(td.set(keys.ACTION, actions[t]))
        q, qd = td[keys.NEXT_Q].double(), td[keys.NEXT_QD].double()
        expected = task.reward_at(q, qd, actions[t].double(), torch.tensor(t))
        assert float(td[keys.NEXT_REWARD]) == pytest.approx(float(expected), rel=1e-5)
        td = td[keys.NEXT]
    system = track.system
    model = system.mj_model()
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = start.q.numpy(), start.qd.numpy()
    by_hand, alive = 0.0, True
    for t in range(3):
        data.ctrl[:] = actions[t].double().numpy()
        mujoco.mj_step(model, data, nstep=system.frame_skip)
        q, qd = torch.from_numpy(data.qpos.copy()), torch.from_numpy(data.qvel.copy())
        step = torch.tensor(5 + t)
        if alive:  # rewards up to and including the step that terminates
            by_hand += float(task.reward_at(q, qd, actions[t].double(), step))
        alive = alive and not bool(task.terminated_at(q, qd, step))
    with mujoco_objective_factory(system, task, nthread=1) as factory:
        got = factory(start.q, start.qd, step=5)(actions[None, :3].double())
    assert float(got) == pytest.approx(by_hand, rel=1e-9)


# ---------------------------------------------------------------- cmu_track's terms


def test_reference_states_score_one_and_time_picks_the_frame(track) -> None:
    task = track.task
    assert isinstance(task, MotionTracking) and task.time_indexed
    assert task.episode_len == task.ref_q.shape[0] - 1
    q, qd, a = task.ref_q[6], task.ref_qd[6], torch.zeros(track.system.nu, dtype=torch.float64)
    assert float(task.reward_at(q, qd, a, torch.tensor(5))) == pytest.approx(1.0)
    assert float(task.reward_at(q, qd, a, torch.tensor(20))) < 0.9  # another frame
    last = task.ref_q.shape[0] - 1  # past the end: scored against the last frame
    ends = task.reward_at(task.ref_q[last], task.ref_qd[last], a, torch.tensor([last, last + 9]))
    torch.testing.assert_close(ends, torch.ones(2, dtype=torch.float64))
    with pytest.raises(TypeError, match="reward_at"):
        task.reward(q, qd, a)


def test_terms_worked_examples(track) -> None:
    """One hinge off by 0.2 rad: pose = exp(-2 0.04); one DoF 3 rad/s too fast: velocity =
    exp(-0.1 9); the whole body moved 0.1 m along x: root = exp(-10 0.01), end effectors and
    pose untouched; moved 0.6 m the episode ends (fail distance 0.5 m), 0.4 m it does not."""
    task, layout = track.task, track.system.layout
    step = torch.tensor(9)
    q, qd = task.ref_q[10].clone(), task.ref_qd[10].clone()
    bent = q.clone()
    bent[20] += 0.2  # a hinge (free root: q[0:7])
    terms = task.terms(bent, qd, step)
    assert float(terms.pose) == pytest.approx(np.exp(-2.0 * 0.04))
    assert float(terms.velocity) == pytest.approx(1.0)
    fast = qd.clone()
    fast[30] += 3.0
    assert float(task.terms(q, fast, step).velocity) == pytest.approx(np.exp(-0.1 * 9.0))
    for dx, ends in ((0.1, False), (0.4, False), (0.6, True)):
        moved = q.clone()
        moved[0] += dx
        terms = task.terms(moved, qd, step)
        assert float(terms.root) == pytest.approx(np.exp(-10.0 * dx**2))
        assert float(terms.pose) == pytest.approx(1.0)
        assert float(terms.end_effector) == pytest.approx(1.0)
        assert bool(task.terminated_at(moved, qd, step)) is ends
    # turning the root turns the end effectors about it: that term drops, the root's does not
    turned = integrate_pos(
        layout, q, torch.zeros(track.system.nv).index_fill(0, torch.tensor([5]), 0.3), 1.0
    )
    terms = task.terms(turned, qd, step)
    assert float(terms.root) == pytest.approx(1.0)
    assert float(terms.end_effector) < 0.9
    assert float(terms.pose) == pytest.approx(np.exp(-2.0 * 0.09))


def test_distances_worked_examples(track) -> None:
    """The reached reference: 0 m; the whole body moved 0.3 m: the root 0.3 m off, the end
    effectors (relative to the root) 0 m; the root turned by 0.3 rad about its vertical axis:
    the root 0 m off, each end effector by 2 sin(0.15) times its horizontal distance from the
    root's vertical axis. An episode's errors average these over its steps."""
    task, layout, nv = track.task, track.system.layout, track.system.nv
    step = torch.tensor(9)
    q = task.ref_q[10].clone()
    at_ref = task.distances(q, step)
    assert float(at_ref.root) == pytest.approx(0.0, abs=1e-12)
    torch.testing.assert_close(at_ref.end_effector, torch.zeros(5, dtype=torch.float64))
    moved = q.clone()
    moved[1] += 0.3
    d = task.distances(moved, step)
    assert float(d.root) == pytest.approx(0.3)
    torch.testing.assert_close(d.end_effector, torch.zeros(5, dtype=torch.float64))
    turned = integrate_pos(layout, q, torch.zeros(nv).index_fill(0, torch.tensor([5]), 0.3), 1.0)
    d = task.distances(turned, step)
    assert float(d.root) == pytest.approx(0.0, abs=1e-9)
    model = track.system.mj_model()
    data = mujoco.MjData(model)
    data.qpos[:] = q.numpy()
    mujoco.mj_kinematics(model, data)
    root = torch.from_numpy(data.xpos[task.root_body].copy())
    axis = torch.from_numpy(data.xmat[task.root_body].reshape(3, 3)[:, 2].copy())  # body z
    ee = torch.from_numpy(data.xpos[task.bodies.numpy()].copy()) - root  # (E, 3)
    radial = ee - (ee @ axis).unsqueeze(-1) * axis  # (E, 3) off the axis
    expected = 2.0 * np.sin(0.15) * torch.linalg.vector_norm(radial, dim=-1)
    torch.testing.assert_close(d.end_effector, expected, atol=1e-9, rtol=1e-6)
    assert float(expected.min()) > 0.01


def test_weights_option_weighs_the_terms(track) -> None:
    """With weights (pose 0.5, velocity 0, end effector 0, root 0.5), a state off by 0.2 rad in
    one hinge and 0.1 m at the root scores 0.5 exp(-2 0.04) + 0.5 exp(-10 0.01)."""
    weights = {"pose": 0.5, "velocity": 0.0, "end_effector": 0.0, "root": 0.5}
    task = make_env_parts("cmu_track", task_options={**RUN_CLIP, "weights": weights}).task
    assert task.weights == TrackingWeights(**weights)
    q, qd = task.ref_q[10].clone(), task.ref_qd[10].clone()
    q[20] += 0.2
    q[0] += 0.1
    expected = 0.5 * np.exp(-2.0 * 0.04) + 0.5 * np.exp(-10.0 * 0.01)
    reward = task.reward_at(q, qd, torch.zeros(track.system.nu), torch.tensor(9))
    assert float(reward) == pytest.approx(expected)
    assert track.task.weights == TrackingWeights()  # no option: the defaults
    scaled = make_env_parts("cmu_track", task_options={**RUN_CLIP, "scales": {"pose": 0.5}}).task
    assert scaled.scales == TrackingScales(pose=0.5)
    assert float(scaled.terms(q, qd, torch.tensor(9)).pose) == pytest.approx(np.exp(-0.5 * 0.04))


def test_env_config_terms_are_the_task_defaults() -> None:
    """configs/env/cmu_track.yaml spells out the default weights and scales (so that one term
    can be overridden from the command line); they must not drift apart."""
    cfg = OmegaConf.load(CONFIG_DIR / "env" / "cmu_track.yaml")
    assert TrackingWeights(**cfg.task.weights) == TrackingWeights()
    assert TrackingScales(**cfg.task.scales) == TrackingScales()


@pytest.mark.parametrize(
    ("weights", "message"),
    [
        ({"pose": 1.0, "balance": 0.0}, "no term balance"),
        ({"pose": "high"}, "not numbers"),
        ([0.3, 0.7], "mapping of term -> number"),
        ({"pose": 0.9}, "add to 1"),
        ({"pose": float("nan")}, "finite"),
    ],
)
def test_bad_weights_are_named(weights: object, message: str, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=message):
        make_env_parts("cmu_track", task_options={**RUN_CLIP, "weights": weights})
    # refused before the clip is looked for: no clip here, and no download
    nowhere = {"folders": [str(tmp_path)], "cache_dir": str(tmp_path), "download": False}
    with pytest.raises(ValueError, match=message):
        make_env_parts("cmu_track", task_options={**nowhere, "weights": weights})


@pytest.mark.parametrize(
    ("scales", "message"),
    [({"pose": 0.0}, "finite and > 0"), ({"reach": 1.0}, "scales: no term reach")],
)
def test_bad_scales_are_named(scales: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        make_env_parts("cmu_track", task_options={**RUN_CLIP, "scales": scales})


def test_initial_state_is_the_first_reference_frame(track) -> None:
    task = track.task
    state = task.initial_state((3,), torch.Generator().manual_seed(0))
    torch.testing.assert_close(state.q[:, :7], task.ref_q[0, :7].expand(3, 7))
    assert float((state.q - task.ref_q[0]).abs().max()) <= task.q_noise
    assert float((state.qd - task.ref_qd[0]).abs().max()) <= task.q_noise


def test_reference_poses_follow_an_episode_and_hold_the_last_frame(track) -> None:
    ref_q = track.task.ref_q  # (T+1, nq)
    poses = track.task.reference_poses(ref_q.shape[0] + 3)  # an episode of T + 4 states
    torch.testing.assert_close(poses[: ref_q.shape[0]], ref_q)
    torch.testing.assert_close(poses[-3:], ref_q[-1].expand(3, -1))
    torch.testing.assert_close(track.task.reference_poses(2), ref_q[:2])


def test_bad_options_and_references_are_named(track) -> None:
    with pytest.raises(ValueError, match="takes no task option clip"):
        make_env_parts("pendulum", task_options={"clip": "02_01"})
    with pytest.raises(ValueError, match="speed"):
        make_env_parts("cmu_track", task_options={**RUN_CLIP, "speed": 1.0})
    with pytest.raises(ValueError, match="ground='no' is not valid; it must be true or false"):
        make_env_parts("cmu_track", task_options={**RUN_CLIP, "ground": "no"})
    task, system = track.task, track.system
    ref_q = task.ref_q.clone()
    ref_q[3, 10] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        MotionTracking(system.mj_model(), system.layout, ref_q, task.ref_qd)
    with pytest.raises(ValueError, match="rows"):
        MotionTracking(system.mj_model(), system.layout, task.ref_q, task.ref_qd[:-1])
    pendulum = make_env_parts("pendulum").system
    with pytest.raises(ValueError, match="free root"):
        MotionTracking(pendulum.mj_model(), pendulum.layout, task.ref_q, task.ref_qd)


# ---------------------------------------------------------------- the reference meets the floor


def test_grounded_reference_stands_on_the_floor_and_ignores_a_lift(track) -> None:
    task, system = track.task, track.system  # 09_06: a run, with flight phases
    model, dt = system.mj_model(), system.control_dt
    clearance = floor_clearance(model, task.ref_q)
    assert float(clearance.min()) > -0.015  # stance: feet at the floor, not in it
    assert float(clearance.max()) > 0.03  # flight: above it
    for half in clearance.split(clearance.shape[0] // 2)[:2]:  # a stance in each half second
        assert abs(float(half.min())) < 0.015
    # lifting the clip (as retargeting leaves it) changes nothing
    time = torch.arange(task.ref_q.shape[0], dtype=torch.float64) * dt
    for lift, rate, tol in ((0.07, 0.0, 1e-9), (0.07, 0.02, 5e-3)):
        lifted_q, lifted_qd = task.ref_q.clone(), task.ref_qd.clone()
        lifted_q[:, 2] += lift + rate * time
        lifted_qd[:, 2] += rate
        q, qd = ground_reference(model, lifted_q, lifted_qd, dt)
        torch.testing.assert_close(q, task.ref_q, atol=tol, rtol=0)
        torch.testing.assert_close(qd, task.ref_qd, atol=tol, rtol=0)
    # the shift moves every body by the same height: the clearance rises by exactly it
    lifted = floor_clearance(model, lifted_q)
    torch.testing.assert_close(lifted - clearance, lift + rate * time, atol=1e-9, rtol=0)


def test_ungrounded_clip_is_the_retargeted_one(track) -> None:
    raw = make_env_parts("cmu_track", task_options={**RUN_CLIP, "ground": False}).task
    shift = track.task.ref_q - raw.ref_q
    assert torch.equal(shift[:, [0, 1, *range(3, shift.shape[1])]], torch.zeros_like(shift[:, :-1]))
    assert float(shift[:, 2].abs().max()) > 0  # the clip is moved, only vertically
