"""The optional compiled planning step and objective give the eager results."""

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch._dynamo.utils import counters
from torch.nn import functional as F

from mbrl_delan import keys
from mbrl_delan.accelerate import CompiledLoop, CompiledStep
from mbrl_delan.accelerate.compile import FitGraph, compile_fit
from mbrl_delan.conf.checks import CONFIG_DIR
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.delan import DeLaN, Stepping
from mbrl_delan.models.inverse import DeLaNInverse
from mbrl_delan.models.kernels import SMALL_SOLVE, activate, log1p_unit, unrolled_cholesky_solve
from mbrl_delan.models.structure import Structure
from mbrl_delan.models.tangent_mlp import TangentMLP
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.planners.mppi import MPPIPlanner
from mbrl_delan.planners.policy import PlannerPolicy, intra_op_threads
from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.systems.system import load_system
from mbrl_delan.tasks.pendulum import PendulumSwingup


@pytest.mark.slow
def test_compiled_step_equals_eager_step() -> None:
    """`CompiledStep` (TorchRL's planners over a compiled model) steps as the model does, and
    compiles only without autograd."""
    system = load_system("acrobot")
    torch.manual_seed(0)
    model = DeLaN(system.layout, system.actuation.float(), system.control_dt, Structure(hidden=16))
    g = torch.Generator().manual_seed(1)
    q, qd, a = (torch.randn(8, k, generator=g) for k in (system.nq, system.nv, system.nu))
    eager = model.step(q, qd, a)
    counters.clear()
    with torch.inference_mode():
        compiled = CompiledStep(model).step(q, qd, a)
    assert counters["stats"]["unique_graphs"] >= 1  # the compiled path ran
    torch.testing.assert_close(compiled.q, eager.q, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(compiled.qd, eager.qd, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_two_compiled_models_in_one_process_step_as_their_own() -> None:
    """Two models whose steps share code but not their settings (control periods dt and 2 dt):
    each compiled step equals its own eager step (a graph traced for the first is not reused)."""
    system = load_system("acrobot")
    torch.manual_seed(0)
    models = [DeLaN(system.layout, system.actuation.float(), k * system.control_dt,
                    Structure(hidden=16)) for k in (1, 2)]  # fmt: skip
    models[1].load_state_dict(models[0].state_dict())
    g = torch.Generator().manual_seed(1)
    q, qd, a = (torch.randn(8, k, generator=g) for k in (system.nq, system.nv, system.nu))
    with torch.inference_mode():
        steps = [CompiledStep(m).step(q, qd, a) for m in models]
    for model, compiled in zip(models, steps, strict=True):
        torch.testing.assert_close(compiled.q, model.step(q, qd, a).q, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(steps[0].q, steps[1].q)  # the settings differ in the result


def test_unrolled_cholesky_solve_equals_lapack() -> None:
    g = torch.Generator().manual_seed(0)
    for n in range(1, SMALL_SOLVE + 1):
        a = torch.randn(5, n, n, generator=g, dtype=torch.float64)
        L = torch.linalg.cholesky(a @ a.mT + n * torch.eye(n, dtype=torch.float64))
        b = torch.randn(5, n, generator=g, dtype=torch.float64)
        x = unrolled_cholesky_solve(L, b)
        torch.testing.assert_close(x, torch.cholesky_solve(b.unsqueeze(-1), L).squeeze(-1))
        torch.testing.assert_close((L @ L.mT @ x.unsqueeze(-1)).squeeze(-1), b)


@pytest.mark.slow
def test_compiled_softplus_and_slope_match_eager_at_extremes() -> None:
    z = torch.cat([torch.linspace(-100.0, 100.0, 401), torch.tensor([0.0, -1e-8, 1e-8])])
    value, slope = torch.compile(lambda x: activate("softplus", x), dynamic=False)(z)
    torch.testing.assert_close(value, F.softplus(z), rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(slope, torch.sigmoid(z), rtol=1e-6, atol=1e-7)


class _AngleReward(PendulumSwingup):
    """The angle as reward: rewards differ every step."""

    def reward(self, q: torch.Tensor, qd: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return q[..., 0] + 0.1 * action[..., 0]


class _EndsPastAngle(_AngleReward):
    """Ended once the angle passes 0.4 rad."""

    def terminated(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        return q[..., 0] > 0.4


class _GraphBreak(PendulumSwingup):
    """A reward the compiler cannot capture in one graph."""

    def reward(self, q: torch.Tensor, qd: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        torch._dynamo.graph_break()
        return super().reward(q, qd, action)


def _pendulum_model() -> DeLaN:
    system = make_env_parts("pendulum").system
    torch.manual_seed(0)
    return DeLaN(
        system.layout, system.actuation.float(), system.control_dt, Structure(hidden=16)
    ).eval()


@pytest.mark.slow
def test_compiled_planning_objective_masks_ended_steps_and_discounts_as_eager() -> None:
    model, task = _pendulum_model(), _EndsPastAngle()
    q0, qd0 = torch.tensor([0.2]), torch.tensor([0.0])
    actions = 2.0 * torch.randn(64, 8, 1, generator=torch.Generator().manual_seed(3))
    eager = model_objective_factory(model, task, discount=0.9)(q0, qd0)(actions)
    never_ends = model_objective_factory(model, _AngleReward(), discount=0.9)
    unmasked = never_ends(q0, qd0)(actions)
    ended = (eager - unmasked).abs() > 1e-3
    assert 0 < int(ended.sum()) < 64  # some sequences end inside the horizon, some do not
    factory = model_objective_factory(model, task, discount=0.9, compile=True)
    graphs = counters["stats"]["unique_graphs"]
    compiled = factory(q0, qd0)(actions)
    assert factory._compiled_loop is not None and factory._loop_compiles  # the loop ran
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-5)
    # one graph for all H steps of a batch size, reused from another start
    factory(q0 + 0.1, qd0)(actions)
    assert counters["stats"]["unique_graphs"] - graphs == 1


@pytest.mark.slow
def test_compiled_loop_of_a_two_dof_model_equals_eager() -> None:
    parts = make_env_parts("acrobot")
    torch.manual_seed(0)
    model = DeLaN(
        parts.system.layout,
        parts.system.actuation.float(),
        parts.system.control_dt,
        Structure(hidden=16),
    ).eval()
    q0, qd0 = torch.tensor([2.5, -0.5]), torch.tensor([1.0, -2.0])
    actions = torch.randn(16, 5, 1, generator=torch.Generator().manual_seed(4))
    eager = model_objective_factory(model, parts.task, discount=0.95)(q0, qd0)(actions)
    factory = model_objective_factory(model, parts.task, discount=0.95, compile=True)
    compiled = factory(q0, qd0)(actions)
    assert factory._compiled_loop is not None and factory._loop_compiles
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-6)
    assert float(eager.std()) > 1e-3  # the sequences score differently


@pytest.mark.slow
def test_a_loop_that_does_not_compile_falls_back_to_compiled_steps() -> None:
    model, task = _pendulum_model(), _GraphBreak()
    q0, qd0 = torch.tensor([0.3]), torch.tensor([-1.0])
    actions = torch.randn(8, 4, 1, generator=torch.Generator().manual_seed(5))
    eager = model_objective_factory(model, task)(q0, qd0)(actions)
    factory = model_objective_factory(model, task, compile=True)
    compiled = factory(q0, qd0)(actions)
    assert not factory._loop_compiles and factory._compiled is not None  # per step
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_compiled_loop_on_worker_threads_equals_eager_with_particles_kept_together() -> None:
    """Five samples of two particles in two shares of three (the last padded): each share's loop
    on its own worker thread, with one intra-op thread, the caller's count left as it was."""
    model, task = _pendulum_model(), _AngleReward()
    q0, qd0 = torch.tensor([0.3]), torch.tensor([-1.0])
    actions = torch.randn(5, 6, 1, generator=torch.Generator().manual_seed(6))
    eager = model_objective_factory(model, task, particles=2, discount=0.95)(q0, qd0)(actions)
    factory = model_objective_factory(
        model, task, particles=2, discount=0.95, compile=True, rollout_threads=2
    )
    graphs = counters["stats"]["unique_graphs"]
    with intra_op_threads(2):  # a caller on two threads (the suite runs on one)
        shared = factory(q0, qd0)(actions)
        assert torch.get_num_threads() == 2
        assert factory._threads is not None
        probe = [q0, qd0]
        counts = factory._threads.map(lambda x: x.new_tensor(torch.get_num_threads()), probe)
    assert [int(c) for c in counts] == [1, 1]
    assert counters["stats"]["unique_graphs"] - graphs == 1  # both shares one size
    assert factory._loop_compiles and factory.planning_threads == 1
    torch.testing.assert_close(shared, eager, rtol=1e-5, atol=1e-5)
    assert float(eager.std()) > 1e-3  # the samples score differently: a mix-up would show
    factory.close()
    assert model_objective_factory(model, task, compile=True, rollout_threads=1)._threads is None


@pytest.mark.slow
def test_compiled_steps_on_worker_threads_equal_eager() -> None:
    """Without the compiled loop (the humanoids' case) the per-step compiled rollouts run in
    shares on the worker threads too, and score as the eager batch does."""
    model, task = _pendulum_model(), _AngleReward()
    q0, qd0 = torch.tensor([0.3]), torch.tensor([-1.0])
    actions = torch.randn(5, 6, 1, generator=torch.Generator().manual_seed(8))
    eager = model_objective_factory(model, task, particles=2, discount=0.95)(q0, qd0)(actions)
    factory = model_objective_factory(
        model, task, particles=2, discount=0.95, compile=True, rollout_threads=2,
        compile_loop=False,
    )  # fmt: skip
    shared = factory(q0, qd0)(actions)
    assert not factory.whole_loop and factory._compiled is not None  # per step
    assert factory.rollout_threads == 2 and factory.planning_threads == 1
    torch.testing.assert_close(shared, eager, rtol=1e-5, atol=1e-5)
    assert float(eager.std()) > 1e-3
    factory.close()


def test_rollout_threads_stop_when_the_loop_runs_uncompiled() -> None:
    """Past the compiler's recompile limit a new batch size runs as Python, where the GIL
    would serialise the shares: the factory goes back to one batch, with the same returns.
    (The loop given back as Python stands in for the compiler giving up.)"""
    model, task = _pendulum_model(), _AngleReward()
    q0, qd0 = torch.tensor([0.3]), torch.tensor([-1.0])
    factory = model_objective_factory(model, task, compile=True, rollout_threads=2)
    factory._compiled_loop = CompiledLoop(factory._looped_returns, compiler=lambda fn: fn)
    actions = torch.randn(5, 3, 1, generator=torch.Generator().manual_seed(7))
    expected = model_objective_factory(model, task)(q0, qd0)(actions)
    torch.testing.assert_close(factory(q0, qd0)(actions), expected, rtol=1e-5, atol=1e-5)
    assert factory._compiled_loop.ran_eagerly
    assert factory.rollout_threads == 1 and factory.planning_threads is None


@pytest.mark.slow
def test_policy_plans_alike_with_rollouts_on_worker_threads() -> None:
    """The same seed gives the same plan with the compiled rollouts in shares on worker threads
    (the plan itself on one intra-op thread) as with eager rollouts of the whole batch."""
    model, task = _pendulum_model(), _AngleReward()
    q, qd = torch.tensor([0.3]), torch.tensor([-1.0])
    actions = []
    for compiled in (False, True):
        factory = model_objective_factory(model, task, compile=compiled, rollout_threads=2)
        planner = MPPIPlanner(6, [-2.0], [2.0], num_samples=32, iterations=2, smoothing=0.5)
        policy = PlannerPolicy(planner, factory, seed=3)
        actions.append(torch.stack([policy.act(q, qd) for _ in range(2)]))
        factory.close()
    torch.testing.assert_close(actions[0], actions[1], rtol=1e-4, atol=1e-5)


def test_intra_op_threads_are_put_back() -> None:
    before = torch.get_num_threads()
    with intra_op_threads(2):
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), intra_op_threads(2):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before
    with intra_op_threads(None):
        assert torch.get_num_threads() == before


def test_the_loop_is_not_tried_with_quaternion_joints() -> None:
    humanoid = load_system(humanoid_v5_xml(), name="humanoid")
    model = DeLaN(
        humanoid.layout, humanoid.actuation.float(), humanoid.control_dt, Structure(hidden=8)
    )
    assert not model.loops_compile
    assert _pendulum_model().loops_compile


def test_log1p_unit_polynomial_matches_log1p_on_the_unit_interval() -> None:
    e64 = torch.linspace(0.0, 1.0, 100_001, dtype=torch.float64)
    exact = torch.log1p(e64)
    approx = log1p_unit(e64.float()).double()
    assert float((approx - exact).abs().max()) < 1.3e-7
    # relative accuracy near 0 too (e p(e) has no constant term): softplus of very negative z
    small = torch.logspace(-30, -3, 200, dtype=torch.float64)
    rel = (log1p_unit(small.float()).double() - torch.log1p(small)).abs() / torch.log1p(small)
    assert float(rel.max()) < 1e-6
    assert torch.equal(log1p_unit(e64), torch.log1p(e64))  # float64: log1p itself


def _loss_and_grads(
    model: torch.nn.Module, batch: TensorDict
) -> tuple[dict[str, float], list[torch.Tensor]]:
    """The metrics of `model.loss(batch)` and the gradient of every parameter that gets one."""
    model.zero_grad(set_to_none=True)
    out = model.loss(batch)
    out.loss.backward()
    return out.metrics, [p.grad.clone() for p in model.parameters() if p.grad is not None]


def _assert_same_loss_and_grads(compiled: tuple, eager: tuple, abs: float | None = None) -> None:
    """(metrics, grads) of the compiled fit equal eager autograd's (as `_loss_and_grads` gives)."""
    (metrics, grads), (eager_metrics, eager_grads) = compiled, eager
    for name, value in metrics.items():
        assert value == pytest.approx(eager_metrics[name], rel=1e-5, abs=abs), name
    assert len(grads) == len(eager_grads) > 0
    for grad, ref in zip(grads, eager_grads, strict=True):
        torch.testing.assert_close(grad, ref, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_compiled_fit_loss_and_gradients_equal_eager() -> None:
    """`compile_fit`: the inverse-dynamics loss of a full batch (as the humanoid
    identification fits it) and its gradient come from the compiled graphs and equal eager
    autograd's; a batch of another shape (an epoch's last) runs eagerly. (The one-step term
    compiles the same way; its graph takes several times longer to compile.)"""
    system = load_system("acrobot")
    torch.manual_seed(0)
    model = DeLaN(
        system.layout,
        system.actuation.float(),
        system.control_dt,
        Structure(hidden=16),
        Stepping(loss="inverse"),
    )
    g = torch.Generator().manual_seed(3)
    batch = TensorDict(
        {
            keys.Q: torch.randn(16, system.nq, generator=g),
            keys.QD: torch.randn(16, system.nv, generator=g),
            keys.ACTION: torch.randn(16, system.nu, generator=g),
            keys.NEXT_Q: torch.randn(16, system.nq, generator=g),
            keys.NEXT_QD: torch.randn(16, system.nv, generator=g),
        },
        batch_size=[16],
    )
    model.fit_normalization(batch)

    eager_metrics, eager_grads = _loss_and_grads(model, batch)
    partial = _loss_and_grads(model, batch[:5])
    compile_fit(model)
    metrics, grads = _loss_and_grads(model, batch)
    graph = model.transition_losses
    assert isinstance(graph, FitGraph) and graph.shape == (16, system.nq)
    assert metrics.keys() == eager_metrics.keys()
    _assert_same_loss_and_grads((metrics, grads), (eager_metrics, eager_grads))
    counters.clear()
    partial_compiled = _loss_and_grads(model, batch[:5])  # an epoch's last batch: eager
    assert counters["stats"]["unique_graphs"] == 0
    _assert_same_loss_and_grads(partial_compiled, partial, abs=0.0)


@pytest.mark.slow
def test_compiled_inverse_fit_loss_and_gradients_equal_eager() -> None:
    """`compile_fit` on a `DeLaNInverse` (the mocap fit's model): a full batch's torque loss
    and its gradient come from the compiled graphs and equal eager autograd's; another batch
    shape and calls without autograd run eagerly."""
    system = load_system("acrobot")
    torch.manual_seed(0)
    model = DeLaNInverse(system.layout, Structure(hidden=16, coulomb=True))
    g = torch.Generator().manual_seed(4)
    batch = TensorDict(
        {
            keys.Q: torch.randn(16, system.nq, generator=g),
            keys.QD: torch.randn(16, system.nv, generator=g),
            keys.QDD: torch.randn(16, system.nv, generator=g),
            keys.TAU: 3.0 * torch.randn(16, system.nv, generator=g),
        },
        batch_size=[16],
    )
    model.fit_normalization(batch)

    eager_metrics, eager_grads = _loss_and_grads(model, batch)
    compile_fit(model)
    metrics, grads = _loss_and_grads(model, batch)
    graph = model.member_predictions
    assert isinstance(graph, FitGraph) and graph.shape == (16, system.nv)
    _assert_same_loss_and_grads((metrics, grads), (eager_metrics, eager_grads))
    counters.clear()
    with torch.no_grad():  # evaluation: eager
        model.loss(batch)
    model.loss(batch[:5])  # another batch shape: eager
    assert counters["stats"]["unique_graphs"] == 0


@pytest.mark.slow
def test_train_config_compile_fit_compiles_the_one_step_loss_as_eager() -> None:
    """`accel.compile_fit=true` reaches the loop's DeLaN, and the loop's one-step (forward)
    loss and its gradient from the compiled graph equal eager autograd's."""
    from hydra import compose, initialize_config_dir

    from mbrl_delan.conf.loop import build_world_model
    from mbrl_delan.data.synthetic import dynamics_dataset

    configs = str(CONFIG_DIR)
    with initialize_config_dir(config_dir=configs, version_base=None):
        default = compose("config", overrides=["env=pendulum", "model=delan"])
        cfg = compose("config", overrides=["env=pendulum", "model=delan", "accel.compile_fit=true"])
    system = make_env_parts("pendulum").system
    models = []
    for config in (default, cfg):
        torch.manual_seed(0)
        models.append(build_world_model(config, system, torch.device("cpu"), torch.float32))
    eager, model = models
    assert not isinstance(eager.transition_losses, FitGraph)
    assert isinstance(model.transition_losses, FitGraph) and model.loss_kind == "forward"
    batch = dynamics_dataset(system, 16, torch.Generator().manual_seed(2)).float()
    eager.fit_normalization(batch)
    model.fit_normalization(batch)

    eager_metrics, eager_grads = _loss_and_grads(eager, batch)
    metrics, grads = _loss_and_grads(model, batch)
    assert model.transition_losses.graph is not None  # the compiled path ran
    _assert_same_loss_and_grads((metrics, grads), (eager_metrics, eager_grads), abs=1e-7)


def test_small_input_layers_keep_column_major_weights_with_the_same_values() -> None:
    torch.manual_seed(0)
    mlp = TangentMLP(n_in=2, n_out=3, hidden=8, layers=2)
    first, second = mlp.hidden
    assert first.weight.stride() == (1, 8) and second.weight.is_contiguous()
    # still a trained parameter: every weight gets a gradient
    mlp(torch.randn(4, 2)).out.square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in mlp.parameters())
    mlp.zero_grad(set_to_none=True)
    x = torch.randn(5, 2, generator=torch.Generator().manual_seed(1))
    row_major = F.linear(x, first.weight.contiguous(), first.bias)
    torch.testing.assert_close(F.linear(x, first.weight, first.bias), row_major)
    # the layout survives a dtype move and loading a row-major state dict
    state = {k: v.contiguous() for k, v in mlp.state_dict().items()}
    mlp = mlp.double()
    mlp.load_state_dict(state)
    assert mlp.hidden[0].weight.stride() == (1, 8)
    assert torch.equal(mlp.hidden[0].weight, state["hidden.0.weight"].double())


def test_model_error_compiles_nothing_in_a_compiled_loop(tmp_path: Path) -> None:
    """With accel.compile=true the planning rollouts compile; `model_error` steps the model
    itself, eagerly, over episodes of any length (it once compiled a graph per length, each
    over 100 s on a humanoid)."""
    from mbrl_delan.conf.checks import compose_train_config
    from mbrl_delan.conf.loop import build_loop
    from mbrl_delan.training.loop import model_error, run_episode

    cfg = compose_train_config(["accel.compile=true", "model.hidden=8", "env.episode_len=12"])
    loop, _ = build_loop(cfg, tmp_path)
    assert loop.policy.objective_factory.compile
    loop.collect_random(1)
    loop.fit()
    episode = run_episode(loop.env, loop.random_policy, seed=5, max_steps=12)
    counters.clear()
    for length in (12, 9, 5):
        err = model_error(loop.model, loop.system, episode[:length], horizon=4)
        assert err.one_step > 0 and err.multi_step > 0
    assert not counters["stats"]  # no frame was even traced
