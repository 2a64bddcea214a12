"""The integrator an env's config gives its DeLaN models, driven by MuJoCo's own accelerations,
reproduces the simulator's control step where MuJoCo integrates with RK4 and so does the model:
then a perfect model of the continuous dynamics predicts the env exactly."""

import mujoco
import numpy as np
import pytest
import torch
from torch import Tensor

from mbrl_delan.conf.checks import compose_train_config
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.integrators import integrate


def _model_config(env: str):
    return compose_train_config([f"env={env}", "model=delan"]).model


def _mujoco_accel(model: mujoco.MjModel, ctrl: np.ndarray):
    """(q (B, nq), qd (B, nv)) -> MuJoCo's qacc (B, nv) with the controls (B, nu) held."""
    data = mujoco.MjData(model)

    def accel(q: Tensor, qd: Tensor) -> Tensor:
        out = np.empty(qd.shape)
        for b in range(q.shape[0]):
            data.qpos[:], data.qvel[:], data.ctrl[:] = q[b].numpy(), qd[b].numpy(), ctrl[b]
            mujoco.mj_forward(model, data)
            out[b] = data.qacc
        return torch.from_numpy(out)

    return accel


@pytest.mark.parametrize("env", ["acrobot"])
def test_rk4_envs_model_step_is_mujocos_control_step(env: str) -> None:
    cfg = _model_config(env)
    assert cfg.integrator == "rk4"
    system = make_env_parts(env).system
    model = system.mj_model()
    rng = np.random.default_rng(0)
    batch = 64
    q = rng.uniform(-np.pi, np.pi, (batch, system.nq))
    qd = rng.uniform(-12.0, 12.0, (batch, system.nv))  # fast spins, where a coarse step fails
    ctrl = rng.uniform(-1.0, 1.0, (batch, system.nu))
    expected = np.empty((batch, system.nq + system.nv))
    data = mujoco.MjData(model)
    for b in range(batch):
        data.qpos[:], data.qvel[:], data.ctrl[:] = q[b], qd[b], ctrl[b]
        mujoco.mj_step(model, data, nstep=system.frame_skip)
        expected[b] = np.concatenate([data.qpos, data.qvel])
    step = integrate(
        system.layout,
        _mujoco_accel(model, ctrl),
        torch.from_numpy(q),
        torch.from_numpy(qd),
        system.control_dt,
        cfg.integrator,
        cfg.substeps,
    )
    predicted = torch.cat([step.q, step.qd], dim=-1)
    torch.testing.assert_close(predicted, torch.from_numpy(expected), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("method", ["euler", "rk4"])
def test_positions_move_with_limited_velocities(method: str) -> None:
    """A huge acceleration (a learned model's blow-up) moves a free body no further than its
    velocity limit allows in a step, and leaves it moving at that limit; without a limit it
    flies off."""
    layout = make_env_parts("humanoid_stand").system.layout
    q = torch.zeros(2, 24, dtype=torch.float64)
    q[:, 2], q[:, 3] = 1.4, 1.0  # root at 1.4 m, unit quaternion
    qd = torch.zeros(2, 23, dtype=torch.float64)
    bound = torch.full((23,), 2.0, dtype=torch.float64)

    def accel(q_: Tensor, qd_: Tensor) -> Tensor:
        return torch.full_like(qd_, 1e6)  # m/s^2, rad/s^2

    def limit(q_: Tensor, qd_: Tensor) -> Tensor:
        return torch.clamp(qd_, -bound, bound)

    dt, substeps = 0.015, 2
    held = integrate(layout, accel, q, qd, dt, method, substeps, limit=limit)
    torch.testing.assert_close(held.qd, bound.expand(2, 23))
    assert float((held.q[:, :3] - q[:, :3]).abs().max()) <= 2.0 * dt + 1e-12
    free = integrate(layout, accel, q, qd, dt, method, substeps)
    assert float((free.q[:, :3] - q[:, :3]).abs().max()) > 10.0
