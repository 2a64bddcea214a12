"""Stable humanoid fits: the loop's DeLaN on humanoid_stand, with the env's defaults, learns
from falls without diverging, and stays finite when rolled out."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.conf.checks import build_fit_config, compose_train_config
from mbrl_delan.conf.loop import build_world_model
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.training.fit import fit_model
from mbrl_delan.training.whitebox import MjStepper


@pytest.fixture(scope="module")
def falls() -> TensorDict:
    """2,000 transitions: 40 episodes of 50 control steps of uniform random controls from the
    task's starts, stepped by the env's own physics (the humanoid drops, lands and falls)."""
    parts = make_env_parts("humanoid_stand", None, None)
    system = parts.system
    start = parts.task.initial_state((40,), torch.Generator().manual_seed(0))
    rng = np.random.default_rng(0)
    ctrl = rng.uniform(system.ctrl_low.numpy(), system.ctrl_high.numpy(), (40, 50, system.nu))
    model = system.mj_model()
    stepper = MjStepper(model, system.frame_skip)
    q, qd = stepper(model, start.q.numpy(), start.qd.numpy(), ctrl)
    stepper.close()
    q_all = np.concatenate([start.q.numpy()[:, None], q], 1)
    qd_all = np.concatenate([start.qd.numpy()[:, None], qd], 1)
    flat = lambda x: torch.from_numpy(np.ascontiguousarray(x)).float().reshape(-1, x.shape[-1])  # noqa: E731
    episode = torch.arange(40)[:, None].expand(-1, 50).reshape(-1, 1)
    return TensorDict(
        {
            keys.Q: flat(q_all[:, :-1]), keys.QD: flat(qd_all[:, :-1]), keys.ACTION: flat(ctrl),
            keys.NEXT_Q: flat(q_all[:, 1:]), keys.NEXT_QD: flat(qd_all[:, 1:]),
            keys.EPISODE: episode,
        },
        batch_size=[2000],
    )  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1])
def test_a_humanoid_fit_loss_falls_over_its_first_epochs(falls: TensorDict, seed: int) -> None:
    """humanoid_stand's DeLaN at the env's defaults (lr 3e-3, the root's known units): its
    first epoch's validation loss is below 2 (a fresh model's one-step error is of the order
    of the data's spread), and the loss falls over the first four epochs, finite throughout."""
    torch.manual_seed(seed)
    cfg = compose_train_config(["env=humanoid_stand", "model=delan", "fit.max_epochs=4"])
    model = build_world_model(cfg, make_env_parts("humanoid_stand", None, None).system,
                              torch.device("cpu"), torch.float32)  # fmt: skip
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.model.lr)
    report = fit_model(model, optimizer, falls, build_fit_config(cfg),
                       torch.Generator().manual_seed(seed))  # fmt: skip
    assert all(np.isfinite(report.val_loss)) and all(np.isfinite(report.train_loss))
    assert report.val_loss[0] < 2.0, report.val_loss
    assert report.val_loss[-1] < 0.8 * report.val_loss[0], report.val_loss
    state = model.step(falls[keys.Q][:256], falls[keys.QD][:256], falls[keys.ACTION][:256])
    for _ in range(29):  # 30 open-loop steps: the loop's model-error horizon
        state = model.step(state.q, state.qd, falls[keys.ACTION][:256])
    assert bool(torch.isfinite(state.q).all() and torch.isfinite(state.qd).all())
