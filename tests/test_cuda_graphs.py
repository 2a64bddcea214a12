"""Rollouts replayed from CUDA graphs (`accel.cuda_graph`) score actions as eager calls do.

The CUDA tests run where a GPU is (they are skipped on CI's CPU machine); the CPU tests
check that the option is refused or inert without one.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from mbrl_delan.accelerate import GraphedCalls
from mbrl_delan.benchmarks.planner import build_delan
from mbrl_delan.conf.checks import CONFIG_DIR, ConfigError, validate_train_config
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.objectives.model import model_objective_factory

CONFIGS = CONFIG_DIR
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def parts(env: str, device: str):  # type: ignore[no-untyped-def]
    """The env's task, a DeLaN on its system (random weights, float32) and a start state."""
    env_parts = make_env_parts(env)
    torch.manual_seed(0)
    model = build_delan(env_parts.system).to(device).eval()
    start = env_parts.task.initial_state((), torch.Generator().manual_seed(0))
    return env_parts, model, start


def random_actions(n: int, horizon: int, nu: int, device: str, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return (2 * torch.rand(n, horizon, nu, generator=gen) - 1).to(device)  # (N, H, nu)


def test_graphed_calls_refuse_cpu_inputs() -> None:
    graphed = GraphedCalls(lambda x: 2 * x, watched=lambda: [])
    with pytest.raises(ValueError, match="CUDA"):
        graphed(torch.ones(3))


def test_cuda_graph_is_inert_on_cpu_tensors() -> None:
    env_parts, model, start = parts("pendulum", "cpu")
    plain = model_objective_factory(model, env_parts.task)(start.q, start.qd)
    graphed = model_objective_factory(model, env_parts.task, cuda_graph=True)(start.q, start.qd)
    actions = random_actions(16, 5, env_parts.system.nu, "cpu", seed=1)
    torch.testing.assert_close(graphed(actions), plain(actions), rtol=0, atol=0)


def test_config_refuses_cuda_graph_without_cuda() -> None:
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        bad = compose(config_name="config", overrides=["accel.cuda_graph=true", "device=cpu"])
    with pytest.raises(ConfigError, match="cuda_graph=true needs device=cuda"):
        validate_train_config(bad)


@pytest.mark.parametrize("env", ["humanoid_stand", "cmu_track"])
def test_model_rollouts_read_nothing_on_the_host(env: str) -> None:
    """What a CUDA graph captures must not read a tensor's value on the host (`.item()`, a
    0-dim index tensor): meta tensors have no values, so a rollout that runs on them, the
    time-indexed tracking reward included, can be captured."""
    data = Path(__file__).parent / "data"
    options = {"clip": "09_06", "folders": [str(data)], "download": False}
    env_parts = make_env_parts(env, task_options=options if env == "cmu_track" else None)
    system = env_parts.system
    model = build_delan(system).to("meta")
    q0 = torch.zeros(system.layout.nq, device="meta")
    qd0 = torch.zeros(system.layout.nv, device="meta")
    actions = torch.zeros(8, 3, system.nu, device="meta")  # (N, H, nu)
    objective = model_objective_factory(model, env_parts.task)(q0, qd0, 5)
    assert objective(actions).shape == (8,)


@needs_cuda
@pytest.mark.parametrize("env", ["pendulum", "humanoid_stand"])
def test_replays_score_fresh_actions_as_eager_calls(env: str) -> None:
    env_parts, model, start = parts(env, "cuda")
    eager = model_objective_factory(model, env_parts.task)
    factory = model_objective_factory(model, env_parts.task, cuda_graph=True)
    nu = env_parts.system.nu
    for seed in range(3):  # one capture, then replays of new inputs
        actions = random_actions(64, 6, nu, "cuda", seed)
        torch.testing.assert_close(
            factory(start.q, start.qd)(actions), eager(start.q, start.qd)(actions)
        )
    assert factory._graphs.captured == 1
    other = random_actions(32, 6, nu, "cuda", seed=9)  # a second shape: a second graph
    torch.testing.assert_close(factory(start.q, start.qd)(other), eager(start.q, start.qd)(other))
    assert factory._graphs.captured == 2


@needs_cuda
def test_replays_read_weights_updated_in_place_and_recapture_after_a_move() -> None:
    env_parts, model, start = parts("pendulum", "cuda")
    eager = model_objective_factory(model, env_parts.task)
    factory = model_objective_factory(model, env_parts.task, cuda_graph=True)
    actions = random_actions(64, 8, env_parts.system.nu, "cuda", seed=2)
    before = factory(start.q, start.qd)(actions)
    with torch.no_grad():  # what an optimiser step does: new values, same memory
        for p in model.parameters():
            p.mul_(1.2)
    after = factory(start.q, start.qd)(actions)
    assert not torch.allclose(after, before)
    torch.testing.assert_close(after, eager(start.q, start.qd)(actions))
    model.cpu().cuda()  # new memory: the old graph must not be replayed
    moved = factory(start.q, start.qd)(actions)
    torch.testing.assert_close(moved, eager(start.q, start.qd)(actions))
    assert factory._graphs.captured == 1


@needs_cuda
def test_compiled_steps_replayed_from_a_graph_match_eager() -> None:
    env_parts, model, start = parts("pendulum", "cuda")
    eager = model_objective_factory(model, env_parts.task)
    factory = model_objective_factory(model, env_parts.task, compile=True, cuda_graph=True)
    actions = random_actions(128, 10, env_parts.system.nu, "cuda", seed=3)
    expected = eager(start.q, start.qd)(actions)
    torch.testing.assert_close(factory(start.q, start.qd)(actions), expected)


@needs_cuda
def test_humanoid_reward_on_cuda_matches_the_cpu() -> None:
    task = make_env_parts("humanoid_stand").task
    start = task.initial_state((256,), torch.Generator().manual_seed(4))
    q = start.q + 0.3 * torch.randn(start.q.shape, generator=torch.Generator().manual_seed(5))
    action = torch.rand(256, 17, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    cpu = task.reward(q, start.qd, action)
    gpu = task.reward(q.cuda(), start.qd.cuda(), action.cuda())
    torch.testing.assert_close(gpu.cpu(), cpu)
    assert cpu.std() > 0  # the random poses score differently
