"""CEM and MPPI on known optima, warm starts, the policy wrapper and the MuJoCo oracle."""

from __future__ import annotations

import io

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from test_model_env import DoubleIntegrator, EndlessQuadraticTask
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.envs import make_env_parts, make_real_env
from mbrl_delan.objectives.base import discounted_masked_return
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.objectives.mujoco import mujoco_objective_factory
from mbrl_delan.planners import CEMPlanner, MPPIPlanner, PlannerPolicy, mppi_weights
from mbrl_delan.planners.mppi import ar1_filter
from mbrl_delan.tasks import PendulumSwingup

H, NU = 6, 2
LOW, HIGH = [-1.0, -1.0], [1.0, 1.0]
TOL = 0.05  # first action within TOL of the optimum in every dimension


def quadratic(target: Tensor):
    """returns = -sum_t |a_t - target_t|^2, target (H, nu)."""
    return lambda actions: -(actions - target).square().sum(dim=(1, 2))


def make(kind: str, **overrides: object) -> CEMPlanner | MPPIPlanner:
    if kind == "cem":
        kwargs = dict(num_samples=400, num_elites=40, iterations=12, init_std=None, min_std=1e-3)
        kwargs.update(overrides)
        return CEMPlanner(H, LOW, HIGH, **kwargs)
    kwargs = dict(num_samples=400, iterations=15, temperature=0.1, noise_std=0.2, smoothing=0.0)
    kwargs.update(overrides)
    return MPPIPlanner(H, LOW, HIGH, **kwargs)


TARGET = torch.linspace(-0.6, 0.6, H * NU).reshape(H, NU)


@pytest.mark.parametrize("kind", ["cem", "mppi"])
@pytest.mark.parametrize("seed", [0, 1])
def test_finds_quadratic_optimum(kind: str, seed: int) -> None:
    result = make(kind).plan(quadratic(TARGET), None, torch.Generator().manual_seed(seed))
    assert result.mean.shape == (H, NU) and result.first_action.shape == (NU,)
    assert (result.first_action - TARGET[0]).abs().max() < TOL
    assert (result.mean - TARGET).abs().max() < 0.1
    assert result.best_return <= 0 and result.iteration_best.shape[0] >= 12


def test_smoothed_mppi_finds_quadratic_optimum() -> None:
    """Action smoothing correlates the perturbations; the optimum it converges to is the same."""
    for seed in (0, 1):
        planner = make("mppi", smoothing=0.8)
        result = planner.plan(quadratic(TARGET), None, torch.Generator().manual_seed(seed))
        assert (result.first_action - TARGET[0]).abs().max() < TOL
        assert (result.mean - TARGET).abs().max() < 0.1


def test_ar1_filter_covariance_is_geometric() -> None:
    """F F^T = a^|t - s| exactly: unit variance at every step, correlation a per step apart."""
    horizon, a = 7, 0.7
    filt = ar1_filter(horizon, a, torch.float64, torch.device("cpu"))
    t = torch.arange(horizon, dtype=torch.float64)
    expected = a ** (t[:, None] - t[None, :]).abs()
    torch.testing.assert_close(filt @ filt.T, expected, atol=1e-12, rtol=0)
    assert torch.equal(torch.triu(filt, diagonal=1), torch.zeros_like(filt))  # causal
    torch.testing.assert_close(
        ar1_filter(horizon, 0.0, torch.float64, torch.device("cpu")),
        torch.eye(horizon, dtype=torch.float64),
    )


@pytest.mark.parametrize("smoothing", [0.0, 0.9])
def test_mppi_samples_have_the_asked_correlation(smoothing: float) -> None:
    """First-iteration samples: std noise_std at every step, lag-1 correlation = smoothing."""
    seen: list[Tensor] = []

    def objective(actions: Tensor) -> Tensor:
        seen.append(actions)
        return -actions.square().sum(dim=(1, 2))

    planner = MPPIPlanner(
        20, [-50.0], [50.0], num_samples=20_000, iterations=1, noise_std=2.0, smoothing=smoothing
    )
    planner.plan(objective, None, torch.Generator().manual_seed(0))
    noise = seen[0][..., 0] / 2.0  # (N, H): the mean is zero
    torch.testing.assert_close(noise.std(dim=0), torch.ones(20), atol=0.03, rtol=0)
    lag1 = (noise[:, 1:] * noise[:, :-1]).mean(dim=0)  # (H - 1,)
    torch.testing.assert_close(lag1, torch.full((19,), smoothing), atol=0.03, rtol=0)


@pytest.mark.parametrize("kind", ["cem", "mppi"])
def test_finds_clipped_optimum(kind: str) -> None:
    target = torch.tensor([[2.0, -3.0]]).expand(H, NU)
    seen = []

    def objective(actions: Tensor) -> Tensor:
        seen.append(actions)
        return quadratic(target)(actions)

    result = make(kind).plan(objective, None, torch.Generator().manual_seed(0))
    torch.testing.assert_close(result.first_action, torch.tensor([1.0, -1.0]), atol=TOL, rtol=0)
    samples = torch.cat(seen)
    assert samples.min() >= -1.0 and samples.max() <= 1.0


def test_bounds_per_dimension_and_float64() -> None:
    planner = CEMPlanner(
        H,
        [0.0, -2.0],
        [0.5, -1.0],
        num_samples=100,
        num_elites=10,
        iterations=4,
        init_std=None,
        min_std=1e-3,
        dtype=torch.float64,
    )
    result = planner.plan(
        quadratic(torch.zeros(H, NU, dtype=torch.float64)), None, torch.Generator().manual_seed(0)
    )
    assert result.mean.dtype == torch.float64
    assert (result.mean[:, 0] >= 0).all() and (result.mean[:, 0] <= 0.5).all()
    assert (result.mean[:, 1] >= -2).all() and (result.mean[:, 1] <= -1).all()
    torch.testing.assert_close(
        result.first_action, torch.tensor([0.0, -1.0]).double(), atol=TOL, rtol=0
    )


def test_mppi_weights_finite_at_huge_returns() -> None:
    returns = torch.tensor([1e8, 1e8 - 1.0, 2e8, -1e8, float("nan"), float("-inf")])
    weights = mppi_weights(returns, temperature=1.0)
    assert torch.isfinite(weights).all()
    assert weights.sum().item() == pytest.approx(1.0)
    assert weights[2].item() == pytest.approx(1.0)
    uniform = mppi_weights(torch.full((4,), float("nan")), temperature=1.0)
    torch.testing.assert_close(uniform, torch.full((4,), 0.25))


def test_mppi_plan_finite_at_huge_returns() -> None:
    def objective(actions: Tensor) -> Tensor:
        return 1e8 + 1e6 * quadratic(TARGET)(actions)

    result = make("mppi").plan(objective, None, torch.Generator().manual_seed(0))
    assert torch.isfinite(result.mean).all()
    assert (result.first_action - TARGET[0]).abs().max() < TOL


def test_nan_returns_are_worst() -> None:
    """Samples whose return is NaN never become elites."""

    def objective(actions: Tensor) -> Tensor:
        returns = quadratic(TARGET)(actions)
        return torch.where(actions[:, 0, 0] > 0, torch.nan, returns)

    result = make("cem").plan(objective, None, torch.Generator().manual_seed(0))
    assert torch.isfinite(result.mean).all() and result.first_action[0] <= 0


@pytest.mark.parametrize("fill", ["repeat", "zero"])
def test_shift(fill: str) -> None:
    planner = CEMPlanner(3, [-1.0], [1.0], shift_fill=fill, num_samples=4, num_elites=2)
    mean = torch.tensor([[0.1], [0.2], [0.3]])
    last = 0.3 if fill == "repeat" else 0.0
    torch.testing.assert_close(planner.shift(mean), torch.tensor([[0.2], [0.3], [last]]))
    torch.testing.assert_close(planner.shift(mean, steps=2), torch.tensor([[0.3], [last], [last]]))
    torch.testing.assert_close(planner.shift(mean, steps=5), torch.full((3, 1), last))


def test_zero_fill_respects_bounds() -> None:
    planner = MPPIPlanner(2, [0.5], [1.0], shift_fill="zero")
    torch.testing.assert_close(
        planner.shift(torch.tensor([[0.7], [0.8]])), torch.tensor([[0.8], [0.5]])
    )
    torch.testing.assert_close(planner.initial_mean(), torch.full((2, 1), 0.5))


def test_warm_start_is_used() -> None:
    """One iteration of CEM with tiny std stays at the warm start it was given."""
    planner = CEMPlanner(
        H, LOW, HIGH, num_samples=20, num_elites=5, iterations=1, init_std=1e-4, momentum=0.0
    )
    warm = TARGET.clone()
    result = planner.plan(quadratic(torch.zeros(H, NU)), warm, torch.Generator().manual_seed(0))
    torch.testing.assert_close(result.mean, warm, atol=1e-3, rtol=0)


@pytest.mark.parametrize(
    ("kwargs", "bad"),
    [
        (dict(horizon=0), "horizon"),
        (dict(num_elites=500), "num_elites"),
        (dict(num_elites=0), "num_elites"),
        (dict(iterations=0), "iterations"),
        (dict(momentum=1.0), "momentum"),
        (dict(min_std=-1.0), "min_std"),
        (dict(init_std=0.0), "init_std"),
        (dict(shift_fill="wrap"), "shift_fill"),
        (dict(action_low=[1.0, 1.0]), "action_low"),
        (dict(action_high=[1.0]), "differ in shape"),
    ],
)
def test_cem_validation(kwargs: dict, bad: str) -> None:
    args = dict(horizon=H, action_low=LOW, action_high=[0.5, 0.5], num_samples=100)
    args.update(kwargs)
    with pytest.raises(ValueError, match=bad):
        CEMPlanner(**args)


@pytest.mark.parametrize(
    ("kwargs", "bad"),
    [
        (dict(temperature=0.0), "temperature"),
        (dict(smoothing=1.0), "smoothing"),
        (dict(smoothing=-0.1), "smoothing"),
        (dict(noise_std=-0.1), "init_std"),
        (dict(num_samples=0), "num_samples"),
    ],
)
def test_mppi_validation(kwargs: dict, bad: str) -> None:
    args = dict(horizon=H, action_low=LOW, action_high=HIGH)
    args.update(kwargs)
    with pytest.raises(ValueError, match=bad):
        MPPIPlanner(**args)


def test_objective_shape_checked() -> None:
    with pytest.raises(ValueError, match="objective must return shape"):
        make("mppi").plan(lambda a: a.sum(dim=1), None, torch.Generator())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_plans_on_cuda() -> None:
    gen = torch.Generator(device="cuda").manual_seed(0)
    for kind in ("cem", "mppi"):
        result = make(kind).plan(quadratic(TARGET.cuda()), None, gen)
        assert result.mean.is_cuda
        assert (result.first_action.cpu() - TARGET[0]).abs().max() < TOL


# ---------------------------------------------------------------------------- the policy
def toy_policy(replan_every: int = 1, seed: int = 0) -> PlannerPolicy:
    planner = MPPIPlanner(8, [-1.0], [1.0], num_samples=64, temperature=0.1)
    factory = model_objective_factory(DoubleIntegrator(), EndlessQuadraticTask())
    return PlannerPolicy(planner, factory, replan_every=replan_every, seed=seed)


def test_policy_in_real_env_rollout() -> None:
    env = make_real_env("pendulum", seed=0)
    policy = toy_policy()
    td = env.rollout(5, policy=policy)
    assert td.batch_size == (5,)
    action = td[keys.ACTION]
    assert action.dtype == env.action_spec.dtype and action.shape == (5, 1)
    assert (action.abs() <= 1).all()
    assert policy.plan_mean is not None and policy.plan_mean.shape == (8, 1)
    policy.reset()
    assert policy.plan_mean is None


def states(n: int) -> list[TensorDict]:
    g = torch.Generator().manual_seed(123)
    return [
        TensorDict({keys.Q: torch.randn(1, generator=g), keys.QD: torch.randn(1, generator=g)})
        for _ in range(n)
    ]


def test_policy_replans_every_k() -> None:
    policy = toy_policy(replan_every=3)
    calls = []
    inner = policy.objective_factory
    policy.objective_factory = lambda q, qd: calls.append(1) or inner(q, qd)
    actions = [policy(td)[keys.ACTION] for td in states(7)]
    assert len(calls) == 3  # steps 0, 3, 6
    plan = policy.last_result.mean
    torch.testing.assert_close(actions[6], plan[0])


@pytest.mark.parametrize("replan_every", [1, 2])
def test_policy_checkpoint_resumes_identically(replan_every: int) -> None:
    tds = states(7)
    policy = toy_policy(replan_every)
    for td in tds[:3]:
        policy(td.clone())
    buffer = io.BytesIO()
    torch.save(policy.state_dict(), buffer)
    expected = [policy(td.clone())[keys.ACTION] for td in tds[3:]]
    restored = toy_policy(replan_every, seed=99)
    buffer.seek(0)
    restored.load_state_dict(torch.load(buffer))
    got = [restored(td.clone())[keys.ACTION] for td in tds[3:]]
    torch.testing.assert_close(torch.stack(got), torch.stack(expected), atol=0, rtol=0)


def test_policy_resets_at_step_count_zero() -> None:
    policy = toy_policy(replan_every=4)
    td = states(1)[0]
    policy(td.clone())
    first_plan = policy.plan_mean
    td[keys.STEP_COUNT] = torch.zeros(1, dtype=torch.int64)
    policy(td.clone())
    assert policy.plan_mean is not first_plan  # replanned from scratch


# ---------------------------------------------------------------------------- the oracle
class PendulumWithLimit(PendulumSwingup):
    """Terminates once |q| > 0.3, to test done masking."""

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        return q[..., 0].abs() > 0.3


def mj_step_return(system, task, q0, qd0, actions: np.ndarray, discount: float) -> float:
    """Plain mj_step loop: the reference the oracle must match."""
    model = system.mj_model()
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = q0, qd0
    total, alive = 0.0, True
    low, high = system.ctrl_low.numpy(), system.ctrl_high.numpy()
    for t, action in enumerate(actions):
        ctrl = np.clip(action, low, high)
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data, nstep=system.frame_skip)
        q, qd = torch.from_numpy(data.qpos.copy()), torch.from_numpy(data.qvel.copy())
        if alive:
            total += discount**t * float(task.reward(q, qd, torch.from_numpy(ctrl)))
        alive = alive and not bool(task.terminated(q, qd))
    return total


@pytest.mark.parametrize(
    ("task", "discount"), [(PendulumSwingup(), 1.0), (PendulumWithLimit(), 0.9)]
)
def test_oracle_matches_mj_step_loop(task: PendulumSwingup, discount: float) -> None:
    system = make_env_parts("pendulum").system
    q0, qd0 = np.array([0.1]), np.array([-0.2])
    g = torch.Generator().manual_seed(0)
    actions = 1.5 * torch.randn(7, 12, 1, generator=g, dtype=torch.float64)  # some clipped
    with mujoco_objective_factory(system, task, nthread=2, discount=discount) as factory:
        objective = factory(torch.from_numpy(q0), torch.from_numpy(qd0))
        returns = objective(actions)
        again = objective(actions)  # MjData reused across calls
    expected = [mj_step_return(system, task, q0, qd0, a.numpy(), discount) for a in actions]
    torch.testing.assert_close(returns, torch.tensor(expected, dtype=torch.float64))
    torch.testing.assert_close(again, returns, atol=0, rtol=0)


def test_oracle_float32_actions_and_states() -> None:
    parts = make_env_parts("pendulum")
    with mujoco_objective_factory(parts.system, parts.task, nthread=1) as factory:
        objective = factory(torch.zeros(1), torch.zeros(1))
        rollout = objective.rollout(torch.ones(3, 4, 1))
        returns = objective(torch.ones(3, 4, 1))
    assert returns.dtype == torch.float32 and returns.shape == (3,)
    assert rollout.states.q.shape == (3, 4, 1) and rollout.states.q.dtype == torch.float64
    assert (rollout.states.q[:, -1] > 0).all()  # positive torque swings towards +q


def test_discounted_masked_return() -> None:
    rewards = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    terminated = torch.tensor([[False, True, False, True]])
    assert discounted_masked_return(rewards, terminated).item() == 3.0
    assert discounted_masked_return(rewards, terminated, 0.5).item() == 2.0


def oracle_mppi_episode(
    env_name: str, horizon: int, steps: int, seed: int, temperature: float, noise_std: float
) -> TensorDict:
    """One episode of MPPI (N 128, one iteration, a plan every 2 steps) on MuJoCo's dynamics."""
    parts = make_env_parts(env_name)
    system, task = parts.system, parts.task
    planner = MPPIPlanner(
        horizon,
        system.ctrl_low,
        system.ctrl_high,
        num_samples=128,
        iterations=1,
        temperature=temperature,
        noise_std=noise_std,
        smoothing=0.0,
    )
    env = make_real_env(env_name, seed=seed)
    with mujoco_objective_factory(system, task, nthread=2) as factory:
        policy = PlannerPolicy(planner, factory, replan_every=2, seed=seed)
        return env.rollout(steps, policy=policy)


@pytest.mark.slow
def test_oracle_mppi_swings_pendulum_up() -> None:
    """The torque limit (0.31 m g l) needs about 100 control steps of pumping; N = 128 keeps
    the test near 15 s on two busy cores (N = 256 also swings up, at twice the cost)."""
    td = oracle_mppi_episode("pendulum", 30, 110, seed=0, temperature=0.01, noise_std=0.8)
    q = td[keys.NEXT_Q][:, 0].double()
    upright = 0.5 * (1 - torch.cos(q))  # 1 = straight up
    assert upright[-10:].mean() > 0.8, upright[::10]


@pytest.mark.slow
def test_oracle_mppi_swings_up_and_balances_the_cartpole() -> None:
    """From the hanging start: the pole is up for the last 50 of 150 control steps (2 s) with
    the cart near the middle of the rail. The test takes about 7 s (it swings up in 50 to 80
    steps on seeds 0 to 2)."""
    td = oracle_mppi_episode("cartpole", 40, 150, seed=1, temperature=0.5, noise_std=0.5)
    assert td.shape[0] == 150
    q = td[keys.NEXT_Q].double()
    upright = 0.5 * (1 - torch.cos(q[:, 1]))  # 1 = pole straight up
    assert upright[:10].max() < 0.1  # it did start hanging
    assert upright[-50:].min() > 0.95, upright[::10]
    assert q[-50:, 0].abs().max() < 0.5, q[-50:, 0]  # cart x, m


def test_warm_start_keywords_reach_only_planners_that_take_them() -> None:
    """`plan(**warm)` goes to `_warm_distribution`: CEM and MPPI take none."""
    for kind in ("cem", "mppi"):
        planner = make(kind, iterations=1)
        assert planner.warm_start({}, 1) == {}
        with pytest.raises(TypeError, match="init_elites"):
            planner.plan(quadratic(TARGET), None, torch.Generator(), init_elites=TARGET[None])
