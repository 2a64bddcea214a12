"""The real env: TorchRL specs, agreement with a direct MuJoCo simulation, rewards, errors."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from mbrl_delan import keys
from mbrl_delan.envs import (
    MujocoTaskEnv,
    env_parts_of,
    gym_id,
    make_env_parts,
    make_real_env,
    register_envs,
)
from mbrl_delan.registry import ENVS

ENV_NAMES = ENVS.names()

# cmu_track's clip: the test data's (its default, 02_01, may not be on the machine)
TASK_OPTIONS = {
    "cmu_track": {
        "clip": "09_06",
        "folders": [str(Path(__file__).parent / "data")],
        "download": False,
    }
}


@pytest.mark.parametrize("name", ENV_NAMES)
def test_check_env_specs(name: str) -> None:
    env = make_real_env(name, seed=0, task_options=TASK_OPTIONS.get(name))
    check_env_specs(env)
    parts = env_parts_of(env)
    assert env.observation_spec[keys.Q].shape == (parts.system.nq,)
    assert env.observation_spec[keys.QD].shape == (parts.system.nv,)
    assert env.action_spec.shape == (parts.system.nu,)
    torch.testing.assert_close(env.action_spec.space.low.double(), parts.system.ctrl_low)
    torch.testing.assert_close(env.action_spec.space.high.double(), parts.system.ctrl_high)


def test_rollout_matches_direct_mujoco_and_task_reward() -> None:
    env = make_real_env("acrobot", seed=3)
    gym_env = env._env.unwrapped
    parts = env_parts_of(env)
    td = env.reset()
    start = gym_env.get_state()  # exact float64 initial state
    np.testing.assert_allclose(td[keys.Q].numpy(), start.q.numpy(), rtol=1e-6)
    actions = 1.5 * torch.randn(30, parts.system.nu, generator=torch.Generator().manual_seed(0))
    steps = []
    for action in actions:  # some actions lie outside [-1, 1] and must be clipped
        td[keys.ACTION] = action.float()
        td = env.step(td)
        steps.append(td.clone())
        td = td["next"]
    # the same controls applied directly in MuJoCo
    model = parts.system.mj_model()
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = start.q.numpy(), start.qd.numpy()
    task = parts.task
    for action, step in zip(actions, steps, strict=True):
        data.ctrl[:] = np.clip(action.numpy().astype(np.float64), -1.0, 1.0)
        for _ in range(parts.system.frame_skip):
            mujoco.mj_step(model, data)
        q, qd = torch.from_numpy(data.qpos.copy()), torch.from_numpy(data.qvel.copy())
        np.testing.assert_allclose(step["next", keys.Q].numpy(), q.numpy(), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(step["next", keys.QD].numpy(), qd.numpy(), rtol=1e-5, atol=1e-5)
        expected = task.reward(q, qd, torch.from_numpy(data.ctrl.copy()))
        assert step["next", keys.REWARD].shape == (1,)
        reward = step["next", keys.REWARD].item()
        assert reward == pytest.approx(expected.item(), rel=1e-5, abs=1e-7)
    assert not any(s["next", keys.DONE].item() for s in steps)


def test_truncation_and_frame_skip_override() -> None:
    env = make_real_env("pendulum", seed=0, frame_skip=2, episode_len=7)
    parts = env_parts_of(env)
    assert parts.system.frame_skip == 2 and parts.task.episode_len == 7
    assert env.wrapper_frame_skip == 1  # our frame_skip is physics steps, not action repeat
    td = env.rollout(100, break_when_any_done=True)
    assert td.shape == (7,)
    assert td["next", keys.TRUNCATED][-1].item() and td["next", keys.DONE][-1].item()
    assert not td["next", keys.TERMINATED].any()
    assert not td["next", keys.DONE][:-1].any()
    # frame_skip=2 means two MuJoCo steps per control step (0.05 s), not TorchRL's action repeat
    gym_env = env._env.unwrapped
    assert gym_env.model.opt.timestep * gym_env.frame_skip == pytest.approx(0.05)


def test_seeding_is_reproducible() -> None:
    first = make_real_env("cartpole", seed=11).reset()
    second = make_real_env("cartpole", seed=11).reset()
    other = make_real_env("cartpole", seed=12).reset()
    assert torch.equal(first[keys.Q], second[keys.Q])
    assert torch.equal(first[keys.QD], second[keys.QD])
    assert not torch.equal(first[keys.Q], other[keys.Q])


def test_unknown_env_name_lists_choices() -> None:
    for make in (make_env_parts, make_real_env):
        with pytest.raises(ValueError, match="'cheetah'") as info:
            make("cheetah")
        assert all(name in str(info.value) for name in ENV_NAMES)


def test_gymnasium_registration_is_idempotent() -> None:
    register_envs()
    register_envs()
    assert gym_id("arm_reach") == "mbrl_delan/ArmReach-v0"
    assert all(gym_id(name) in gym.registry for name in ENV_NAMES)
    env = gym.make(gym_id("arm_reach"), disable_env_checker=True)
    assert isinstance(env.unwrapped, MujocoTaskEnv)
    obs, _ = env.reset(seed=0)
    assert set(obs) == {keys.Q, keys.QD} and obs[keys.Q].dtype == np.float32
    assert env.observation_space[keys.Q].shape == (2,)
    obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
    assert 0.0 <= reward <= 1.0 and not terminated and not truncated


def test_torchrl_keys_are_the_shared_keys() -> None:
    env = make_real_env("pendulum", seed=0)
    td = env.rollout(3)
    assert isinstance(td, TensorDict)
    expected = {keys.Q, keys.QD, keys.ACTION, keys.DONE, keys.TERMINATED, keys.TRUNCATED}
    assert expected <= set(td.keys())
    for key in (keys.Q, keys.QD, keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED):
        assert key in td["next"].keys()
