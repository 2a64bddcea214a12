"""The planner policy inside TorchRL's own machinery: collectors and model-env rollouts."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector  # torchrl 0.14 name of SyncDataCollector
from torchrl.envs import Compose, InitTracker, SerialEnv, TransformedEnv
from torchrl.modules import WorldModelWrapper

from mbrl_delan import keys
from mbrl_delan.envs import ModelEnv, ReturnToGo, make_env_parts, make_real_env
from mbrl_delan.models.base import WorldModel
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.ensemble import GaussianEnsemble
from mbrl_delan.models.structure import Structure
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.objectives.mujoco import mujoco_objective_factory
from mbrl_delan.planners import MPPIPlanner
from mbrl_delan.planners.policy import PlannerPolicy


def pendulum_policy(factory) -> PlannerPolicy:
    system = make_env_parts("pendulum").system
    planner = MPPIPlanner(
        horizon=8, action_low=system.ctrl_low, action_high=system.ctrl_high, num_samples=32
    )
    return PlannerPolicy(planner, factory, seed=0, action_dtype=torch.float32)


def test_collector_with_the_oracle_planner() -> None:
    parts = make_env_parts("pendulum", episode_len=12)
    oracle = mujoco_objective_factory(parts.system, parts.task, nthread=1)
    policy = pendulum_policy(oracle)
    resets = []
    original_reset = policy.reset
    policy.reset = lambda: (resets.append(1), original_reset())[1]
    collector = Collector(
        lambda: TransformedEnv(make_real_env("pendulum", seed=0, episode_len=12), InitTracker()),
        policy,
        frames_per_batch=12,
        total_frames=24,
    )
    resets.clear()  # the collector may probe the policy while it is built
    batches = list(collector)
    collector.shutdown()
    assert len(resets) == 2  # InitTracker: the warm start is dropped at each episode start
    assert len(batches) == 2
    for batch in batches:
        action = batch[keys.ACTION]
        assert action.shape == (12, 1) and action.abs().max() <= 1.0
        assert torch.isfinite(batch[keys.NEXT_REWARD]).all()
        # the planner acted: it did not just return its initial (zero) plan
        assert action.abs().max() > 0.0


def pendulum_env() -> TransformedEnv:
    return TransformedEnv(make_real_env("pendulum", episode_len=12), InitTracker())


def test_planner_policy_collects_from_a_serial_env_with_one_plan_per_env() -> None:
    """SerialEnv(2): one plan per env; env 0 acts exactly as a lone env of the same seed."""
    oracle = mujoco_objective_factory(
        make_env_parts("pendulum").system, make_env_parts("pendulum").task, nthread=1
    )
    batched = SerialEnv(2, pendulum_env)
    batched.set_seed(0)
    policy = pendulum_policy(oracle)
    td = batched.rollout(6, policy=policy)
    batched.close()
    assert td.shape == (2, 6) and td[keys.ACTION].shape == (2, 6, 1)
    assert len(policy._per_env) == 2 and policy.plan_mean is None  # the envs' own plans
    assert not torch.equal(td[0][keys.Q], td[1][keys.Q])  # two envs, two starts
    lone = pendulum_env()
    lone.set_seed(0)
    alone = lone.rollout(6, policy=pendulum_policy(oracle))
    torch.testing.assert_close(td[0][keys.ACTION], alone[keys.ACTION])
    torch.testing.assert_close(td[0][keys.NEXT_Q], alone[keys.NEXT_Q])


def test_envs_that_end_at_different_steps_give_one_whole_episode_each(monkeypatch) -> None:
    """SerialEnv of episodes of 5 and 8 steps: the rollout runs until both end (TorchRL's
    partial steps), the finished env is not planned for, and `split_episodes` cuts each
    env's episode at its own end."""
    from functools import partial

    from mbrl_delan.training.loop import run_episode, split_episodes

    parts = make_env_parts("pendulum")
    oracle = mujoco_objective_factory(parts.system, parts.task, nthread=1)
    batched = SerialEnv(2, [partial(make_real_env, "pendulum", episode_len=n) for n in (5, 8)])
    policy = pendulum_policy(oracle)
    acted: list[int] = []  # the sub-policies asked for an action, by identity
    act = PlannerPolicy.act
    monkeypatch.setattr(
        PlannerPolicy, "act", lambda p, q, qd: (acted.append(id(p)), act(p, q, qd))[1]
    )
    rollout = run_episode(batched, policy, seed=0, max_steps=20)
    batched.close()
    assert rollout.shape == (2, 8)
    episodes = split_episodes(rollout)
    assert [e.shape[0] for e in episodes] == [5, 8]
    for episode in episodes:
        done = episode[keys.NEXT_DONE].reshape(-1)
        assert done[-1] and not done[:-1].any()
    first, second = (id(p) for p in policy._per_env)
    assert acted.count(first) == 5 and acted.count(second) == 8


def test_an_env_without_q_and_qd_gets_their_names() -> None:
    from tensordict import TensorDict

    policy = pendulum_policy(lambda q, qd: None)
    with pytest.raises(KeyError, match="lacks .*'observation'.*q and qd") as err:
        policy(TensorDict({"observation": torch.zeros(3)}))
    assert "'q', 'qd'" in str(err.value)


def test_model_env_rollout_with_a_planner_policy() -> None:
    parts = make_env_parts("pendulum", episode_len=10)
    system = parts.system
    torch.manual_seed(0)
    model = DeLaN(system.layout, system.actuation.float(), system.control_dt, Structure(hidden=16))
    env = ModelEnv(model, parts.task, system)
    policy = pendulum_policy(model_objective_factory(model, parts.task))
    with torch.inference_mode():
        td = env.rollout(5, policy=policy)
    assert td.shape == (5,)
    assert torch.isfinite(td[keys.NEXT_Q]).all() and torch.isfinite(td[keys.NEXT_REWARD]).all()
    # the model env's reward is the task's reward of the reached state
    expected = parts.task.reward(td[keys.NEXT_Q], td[keys.NEXT_QD], td[keys.ACTION])
    torch.testing.assert_close(td[keys.NEXT_REWARD].squeeze(-1), expected.to(td[keys.NEXT_REWARD]))


# ------------------------------------------------- the world model as a TorchRL module


def _pendulum_models() -> dict[str, WorldModel]:
    system = make_env_parts("pendulum").system
    torch.manual_seed(0)
    delan = DeLaN(system.layout, system.actuation.float(), system.control_dt, Structure(hidden=16))
    ensemble = GaussianEnsemble(
        system.layout, system.nu, system.control_dt, ensemble_size=3, hidden=16, propagation="mean"
    )
    return {"delan": delan, "ensemble": ensemble}


@pytest.mark.parametrize("name", ["delan", "ensemble"])
def test_the_torchrl_module_steps_as_the_loops_objective(name: str) -> None:
    """ModelEnv (TorchRL's WorldModelWrapper of the model's TensorDictModule and the task's
    reward) rolled out with fixed actions gives the returns the loop's planning objective
    gives the same action sequences, step for step the model's own `step`."""
    parts = make_env_parts("pendulum", episode_len=10)
    model = _pendulum_models()[name]
    n, horizon = 4, 6
    generator = torch.Generator().manual_seed(1)
    actions = 2 * torch.rand(n, horizon, 1, generator=generator) - 1  # (N, H, nu) in range
    env = ModelEnv(model, parts.task, parts.system, batch_size=(n,))
    start = env.reset()
    objective = model_objective_factory(model, parts.task)(start[keys.Q][0], start[keys.QD][0])
    start[keys.Q], start[keys.QD] = (
        start[keys.Q][:1].expand(n, -1),
        start[keys.QD][:1].expand(n, -1),
    )
    rewards, td = [], start
    for t in range(horizon):
        td[keys.ACTION] = actions[:, t]
        stepped = env.step(td)
        nxt = model.step(td[keys.Q], td[keys.QD], actions[:, t])
        torch.testing.assert_close(stepped[keys.NEXT_Q], nxt.q.to(stepped[keys.NEXT_Q]))
        rewards.append(stepped[keys.NEXT_REWARD].squeeze(-1))
        td = stepped["next"].exclude(keys.REWARD)
    torch.testing.assert_close(torch.stack(rewards, -1).sum(-1), objective(actions))
    wrapper = env.world_model
    assert isinstance(wrapper, WorldModelWrapper)
    assert wrapper.get_transition_model_operator().out_keys == [keys.Q, keys.QD]


def test_torchrl_mppi_plans_on_a_delan_model_env_from_a_real_state() -> None:
    """TorchRL's own MPPIPlanner on the DeLaN ModelEnv with a StepCounter, started from the
    real env's state, which has no step count (TorchRL's StepCounter raised TypeError)."""
    from torchrl.envs import StepCounter
    from torchrl.modules.planners import MPPIPlanner as TorchRLMPPIPlanner

    parts = make_env_parts("pendulum", episode_len=10)
    model = _pendulum_models()["delan"]
    env = TransformedEnv(ModelEnv(model, parts.task, parts.system), StepCounter(max_steps=10))
    planner = TorchRLMPPIPlanner(
        env,
        ReturnToGo(),
        temperature=1.0,
        planning_horizon=5,
        optim_steps=2,
        num_candidates=16,
        top_k=16,
    )
    real = make_real_env("pendulum", seed=0, episode_len=10)
    start = real.reset()
    assert keys.STEP_COUNT not in start.keys()
    action = planner(start.clone())[keys.ACTION]
    assert action.shape == (1,) and torch.isfinite(action).all() and action.abs().max() <= 1.0
    td = real.rollout(3, policy=planner)
    assert td.shape == (3,) and torch.isfinite(td[keys.NEXT_REWARD]).all()


def test_return_to_go_is_each_candidates_reward_to_go_less_the_best_return() -> None:
    """Worked: rewards (1, 2, 3) and (0, 0, 1) have rewards-to-go (6, 5, 3) and (1, 1, 1), the
    best return 6, so the advantages are (0, -1, -3) and (-5, -5, -5)."""
    from tensordict import TensorDict

    reward = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]]).unsqueeze(-1)  # (N, H, 1)
    td = TensorDict({keys.NEXT_REWARD: reward}, batch_size=[2, 3])
    advantage = ReturnToGo()(td)["advantage"].squeeze(-1)
    torch.testing.assert_close(advantage, torch.tensor([[0.0, -1.0, -3.0], [-5.0, -5.0, -5.0]]))


def test_torchrl_mppi_with_return_to_go_stays_finite_at_a_large_temperature() -> None:
    """TorchRL's MPPI weighs by exp(temperature x advantage) with no maximum taken out: at
    temperature 1e4 raw returns overflow; ReturnToGo's shifted advantages keep the plan finite."""
    from torchrl.modules.planners import MPPIPlanner as TorchRLMPPIPlanner

    parts = make_env_parts("pendulum", episode_len=10)
    env = ModelEnv(_pendulum_models()["delan"], parts.task, parts.system)
    planner = TorchRLMPPIPlanner(
        env, ReturnToGo(), temperature=1e4, planning_horizon=5, optim_steps=2,
        num_candidates=16, top_k=16,
    )  # fmt: skip
    start = make_real_env("pendulum", seed=0, episode_len=10).reset()
    action = planner(start.clone())[keys.ACTION]
    assert torch.isfinite(action).all() and action.abs().max() <= 1.0


def test_collector_gathers_imagined_data_with_the_planner_policy() -> None:
    """A TorchRL Collector over the DeLaN ModelEnv (with a StepCounter for episode ends) and
    the project's PlannerPolicy on the same model's objective."""
    from torchrl.envs import StepCounter

    parts = make_env_parts("pendulum", episode_len=6)
    model = _pendulum_models()["delan"]

    def make_env() -> TransformedEnv:
        env = ModelEnv(model, parts.task, parts.system)
        return TransformedEnv(env, Compose(StepCounter(max_steps=6), InitTracker()))

    policy = pendulum_policy(model_objective_factory(model, parts.task))
    collector = Collector(make_env, policy, frames_per_batch=6, total_frames=12)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch[keys.ACTION].shape == (6, 1) and batch[keys.ACTION].abs().max() > 0
        assert batch[keys.NEXT_TRUNCATED][-1].item()  # the episode ends at its 6th step
        assert torch.isfinite(batch[keys.NEXT_Q]).all()
