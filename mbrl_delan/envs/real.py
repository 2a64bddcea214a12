"""The real environment: a MuJoCo system stepped by MuJoCo, scored by a torch task.

`MujocoTaskEnv` is a plain gymnasium env; `make_real_env` wraps it in TorchRL's `GymEnv`.
"""

from __future__ import annotations

import logging
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import torch
from torchrl.envs import GymEnv

from mbrl_delan import keys
from mbrl_delan.envs.registry import EnvParts, TaskOptions, make_env_parts
from mbrl_delan.registry import ENVS
from mbrl_delan.systems.system import State
from mbrl_delan.training.video import VideoRecorder, root_travels

log = logging.getLogger(__name__)


class MujocoTaskEnv(gym.Env):
    """Gymnasium env over `make_env_parts(env_name, ...)`.

    Observation: Dict(q=Box(nq), qd=Box(nv)) float32. Action: Box(ctrl_low, ctrl_high) float32,
    clipped before it is applied for `frame_skip` MuJoCo steps. Reward: task.reward_at on the
    reached (float64) state and the episode step of the action (0 first). Truncated after
    `episode_len` steps.

    `physics_frame_skip` is an alias of `frame_skip` for `make_real_env`: TorchRL's GymEnv
    consumes a `frame_skip` keyword itself (as action repeat), so it cannot reach this class.

    ``render_mode="rgb_array"``: `render` returns the current frame, uint8 (height, width, 3),
    drawn by a `VideoRecorder` (the backend of ``MUJOCO_GL``; a travelling root tracked), so
    gymnasium's ``RecordVideo`` and TorchRL's video recorders work; ``metadata["render_fps"]``
    is the control rate.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        env_name: str,
        frame_skip: int | None = None,
        episode_len: int | None = None,
        *,
        physics_frame_skip: int | None = None,
        task_options: TaskOptions | None = None,
        render_mode: str | None = None,
        width: int = 320,
        height: int = 240,
    ) -> None:
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode={render_mode!r}: the env renders only 'rgb_array'")
        if frame_skip is not None and physics_frame_skip is not None:
            raise ValueError("give frame_skip or physics_frame_skip, not both")
        skip = physics_frame_skip if frame_skip is None else frame_skip
        self.env_name = env_name
        self.env_parts: EnvParts = make_env_parts(env_name, skip, episode_len, task_options)
        system = self.env_parts.system
        self._model = self.env_parts.physics.mj_model()  # what the env simulates
        self._data = mujoco.MjData(self._model)
        self._low = system.ctrl_low.numpy()
        self._high = system.ctrl_high.numpy()
        self._steps = 0
        self.render_mode, self._size = render_mode, (width, height)
        self._video: VideoRecorder | None = None  # made at the first `render`
        self.metadata = {**self.metadata, "render_fps": 1.0 / system.control_dt}
        inf = np.inf
        self.observation_space = gym.spaces.Dict(
            {
                keys.Q: gym.spaces.Box(-inf, inf, (system.nq,), np.float32),
                keys.QD: gym.spaces.Box(-inf, inf, (system.nv,), np.float32),
            }
        )
        self.action_space = gym.spaces.Box(
            self._low.astype(np.float32), self._high.astype(np.float32), dtype=np.float32
        )

    @property
    def frame_skip(self) -> int:
        return self.env_parts.system.frame_skip

    @property
    def episode_len(self) -> int:
        return self.env_parts.task.episode_len

    @property
    def model(self) -> mujoco.MjModel:
        return self._model

    def get_state(self) -> State:
        """The exact simulator state, float64, shapes (nq,), (nv,)."""
        return State(
            q=torch.from_numpy(self._data.qpos.copy()), qd=torch.from_numpy(self._data.qvel.copy())
        )

    def set_state(self, state: State) -> None:
        """Overwrite the simulator state (q (nq,), qd (nv,)); the step counter is kept."""
        self._data.qpos[:] = state.q.detach().cpu().double().numpy()
        self._data.qvel[:] = state.qd.detach().cpu().double().numpy()
        mujoco.mj_forward(self._model, self._data)

    def _obs(self) -> dict[str, np.ndarray]:
        return {
            keys.Q: self._data.qpos.astype(np.float32),
            keys.QD: self._data.qvel.astype(np.float32),
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        generator = torch.Generator().manual_seed(int(self.np_random.integers(2**63 - 1)))
        state = self.env_parts.task.initial_state((), generator)
        mujoco.mj_resetData(self._model, self._data)
        self.set_state(state)
        self._steps = 0
        return self._obs(), {}

    def step(
        self, action: np.ndarray
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        ctrl = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), self._low, self._high)
        self._data.ctrl[:] = ctrl
        mujoco.mj_step(self._model, self._data, nstep=self.frame_skip)
        step = torch.tensor(self._steps)  # the episode step of this action
        self._steps += 1
        state = self.get_state()
        task = self.env_parts.task
        reward = float(task.reward_at(state.q, state.qd, torch.from_numpy(ctrl), step))
        terminated = bool(task.terminated_at(state.q, state.qd, step))
        truncated = self._steps >= task.episode_len
        return self._obs(), reward, terminated, truncated, {}

    def render(self) -> np.ndarray | None:
        """The current frame (``render_mode="rgb_array"``), uint8 (height, width, 3); None
        without a render mode."""
        if self.render_mode is None:
            return None
        if self._video is None:
            width, height = self._size
            self._video = VideoRecorder(
                self._model,
                width,
                height,
                fps=self.metadata["render_fps"],
                track_root=root_travels(self.env_parts.system.layout.types),
                markers=self.env_parts.task.markers(),
            )
        return self._video.frame_from_state(self._data.qpos, self._data.qvel)  # its own MjData

    def close(self) -> None:
        """Free the renderer, if one was made."""
        if self._video is not None:
            self._video.close()
            self._video = None


def gym_id(name: str) -> str:
    """The gymnasium id of a registered env: ``mbrl_delan/<Name>-v0`` (arm_reach: ArmReach)."""
    return "mbrl_delan/" + "".join(part.capitalize() for part in name.split("_")) + "-v0"


def register_gym_id(name: str) -> None:
    """Register env `name`'s gymnasium id, made by `MujocoTaskEnv` (idempotent)."""
    if gym_id(name) not in gym.registry:
        gym.register(id=gym_id(name), entry_point=MujocoTaskEnv, kwargs={"env_name": name})


def register_envs() -> None:
    """Register the gymnasium id (`gym_id`) of every env in the registry, a plugin's
    included (idempotent)."""
    for name in ENVS.names():
        register_gym_id(name)


def make_real_env(
    name: str,
    device: str = "cpu",
    seed: int | None = None,
    frame_skip: int | None = None,
    episode_len: int | None = None,
    task_options: TaskOptions | None = None,
    **kwargs: Any,
) -> GymEnv:
    """TorchRL `GymEnv` over `MujocoTaskEnv(name, frame_skip, episode_len, task_options)`.

    Keys: `q`, `qd` (float32 observations), `action`, `reward`, `done`, `terminated`,
    `truncated`. `frame_skip` is the number of MuJoCo steps per control step (not TorchRL's
    action repeat); `task_options` those of `make_env_parts` (cmu_track: the clip); extra
    `kwargs` go to `GymEnv`. Use `env_parts_of(env)` for the system and task.
    """
    if name not in ENVS:
        raise ValueError(f"unknown env name {name!r}; valid choices: {', '.join(ENVS.names())}")
    register_envs()
    env = GymEnv(
        gym_id(name),
        device=device,
        physics_frame_skip=frame_skip,
        episode_len=episode_len,
        task_options=None if task_options is None else dict(task_options),
        **kwargs,
    )
    if seed is not None:
        env.set_seed(seed)
    return env


def env_parts_of(env: GymEnv) -> EnvParts:
    """The `EnvParts` (system, task) of an env made by `make_real_env`."""
    return env._env.unwrapped.env_parts
