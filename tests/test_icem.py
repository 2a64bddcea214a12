"""iCEM: known optima, colored noise spectra, population decay, kept elites, the advantage
over CEM on a problem with a smooth optimum, the policy and the config."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from test_model_env import DoubleIntegrator, EndlessQuadraticTask
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.conf.builders import build_planner
from mbrl_delan.conf.checks import CONFIG_DIR, validate_train_config
from mbrl_delan.envs import make_env_parts, make_real_env
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.planners import CEMPlanner, ICEMPlanner, PlannerPolicy, colored_noise

H, NU = 6, 2
LOW, HIGH = [-1.0, -1.0], [1.0, 1.0]
TOL = 0.05  # first action within TOL of the optimum in every dimension
TARGET = torch.linspace(-0.6, 0.6, H * NU).reshape(H, NU)
CONFIGS = CONFIG_DIR


def quadratic(target: Tensor):
    """returns = -sum_t |a_t - target_t|^2, target (H, nu)."""
    return lambda actions: -(actions - target).square().sum(dim=(1, 2))


def recording(objective):
    """The objective plus the list of action batches it was called with."""
    seen: list[Tensor] = []

    def wrapped(actions: Tensor) -> Tensor:
        seen.append(actions.clone())
        return objective(actions)

    return wrapped, seen


def make(**overrides: object) -> ICEMPlanner:
    kwargs = dict(num_samples=400, num_elites=40, iterations=12)
    kwargs.update(overrides)
    return ICEMPlanner(H, LOW, HIGH, **kwargs)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------------------- known optima
@pytest.mark.parametrize("beta", [0.0, 2.0])
@pytest.mark.parametrize("seed", [0, 1])
def test_finds_quadratic_optimum(beta: float, seed: int) -> None:
    result = make(beta=beta).plan(quadratic(TARGET), None, gen(seed))
    assert (result.first_action - TARGET[0]).abs().max() < TOL
    assert (result.mean - TARGET).abs().max() < 0.1
    assert result.best_return <= 0


def test_finds_clipped_optimum() -> None:
    target = torch.tensor([[2.0, -3.0]]).expand(H, NU)
    objective, seen = recording(quadratic(target))
    # a floor of 200 keeps the elites (40) at most a fifth of the population; at the default
    # floor 2 K the selection pressure is too weak to reach the bound in 12 iterations
    result = make(min_samples=200).plan(objective, None, gen(0))
    torch.testing.assert_close(result.first_action, torch.tensor([1.0, -1.0]), atol=TOL, rtol=0)
    samples = torch.cat(seen)
    assert samples.min() >= -1.0 and samples.max() <= 1.0
    assert (result.elites.abs() <= 1.0).all()


def test_bounds_per_dimension_and_float64() -> None:
    planner = ICEMPlanner(
        H,
        [0.0, -2.0],
        [0.5, -1.0],
        num_samples=100,
        num_elites=10,
        iterations=5,
        dtype=torch.float64,
    )
    result = planner.plan(quadratic(torch.zeros(H, NU, dtype=torch.float64)), None, gen(0))
    assert result.mean.dtype == torch.float64 and result.elites.dtype == torch.float64
    torch.testing.assert_close(
        result.first_action, torch.tensor([0.0, -1.0]).double(), atol=TOL, rtol=0
    )


def test_return_best_returns_the_best_sequence() -> None:
    objective = quadratic(TARGET)
    result = make(iterations=3, return_best=True).plan(objective, None, gen(0))
    torch.testing.assert_close(result.mean, result.best_actions, atol=0, rtol=0)
    assert objective(result.mean[None]).item() == pytest.approx(result.best_return.item())
    assert result.best_return == result.iteration_best.max()
    # without it, the plan is the distribution mean
    default = make(iterations=3).plan(objective, None, gen(0))
    torch.testing.assert_close(default.mean, default.dist_mean, atol=0, rtol=0)


# ---------------------------------------------------------------------------- colored noise
def mean_power(noise: Tensor) -> Tensor:
    """Average power per rfft bin over samples and dimensions. (N, H, nu) -> (H // 2 + 1,)"""
    return torch.fft.rfft(noise, dim=1).abs().square().mean(dim=(0, 2))


@pytest.mark.parametrize("horizon", [30, 31])
def test_colored_noise_is_red_with_unit_variance(horizon: int) -> None:
    noise = colored_noise((20_000, horizon, 2), beta=2.0, generator=gen(0), dtype=torch.float64)
    var = noise.var(dim=0)  # (H, nu): every step and dimension
    assert (var - 1).abs().max() < 0.06, var
    power = mean_power(noise)
    low = power[1:4].sum() + power[0]  # DC and the 3 lowest frequencies
    assert low / power.sum() > 0.8, power
    assert power[1] > 10 * power[-1]
    lag1 = (noise[:, 1:] * noise[:, :-1]).mean()
    assert lag1 > 0.8


@pytest.mark.parametrize("periodic", [False, True])
def test_colored_noise_beta_zero_is_white(periodic: bool) -> None:
    noise = colored_noise(
        (20_000, 16, 3), beta=0.0, generator=gen(1), dtype=torch.float64, periodic=periodic
    )
    var = noise.var(dim=0)
    assert (var - 1).abs().max() < 0.06
    # the covariance across time is the identity: independent steps
    flat = noise.permute(0, 2, 1).reshape(-1, 16)  # (N * nu, H)
    cov = flat.T @ flat / flat.shape[0]
    off_diagonal = cov - torch.diag(torch.diag(cov))
    assert off_diagonal.abs().max() < 0.03
    power = mean_power(noise)[1:-1]  # complex bins: flat spectrum
    assert (power / power.mean() - 1).abs().max() < 0.1


def test_periodic_noise_follows_the_power_law_exactly() -> None:
    """Periodic noise has power proportional to f^-beta in every bin but DC."""
    horizon, beta = 32, 1.5
    noise = colored_noise(
        (40_000, horizon, 1), beta=beta, generator=gen(2), dtype=torch.float64, periodic=True
    )
    power = mean_power(noise)[1:-1]
    freqs = torch.arange(1, horizon // 2, dtype=torch.float64)
    expected = freqs.pow(-beta)
    ratio = (power / power[0]) / (expected / expected[0])
    assert (ratio - 1).abs().max() < 0.06, ratio


def test_planner_samples_are_smooth() -> None:
    """The planner's first iteration draws mean + std * colored noise."""
    objective, seen = recording(quadratic(torch.zeros(30, 1)))
    for beta, smooth in ((2.0, True), (0.0, False)):
        seen.clear()
        planner = ICEMPlanner(
            30,
            [-10.0],
            [10.0],
            num_samples=2000,
            num_elites=10,
            iterations=1,
            init_std=1.0,
            beta=beta,
        )
        planner.plan(objective, None, gen(0))
        lag1 = (seen[0][:, 1:] * seen[0][:, :-1]).mean()
        assert (lag1 > 0.8) if smooth else (lag1.abs() < 0.05), (beta, lag1)


# ---------------------------------------------------------------------------- population
def test_population_decay_counts_objective_calls() -> None:
    objective, seen = recording(quadratic(TARGET))
    planner = make(num_samples=100, num_elites=10, iterations=5, decay=2.0, min_samples=20)
    result = planner.plan(objective, None, gen(0))
    expected = (100, 50, 25, 20, 20)  # max(20, floor(100 / 2^i))
    assert tuple(batch.shape[0] for batch in seen) == expected
    assert result.population == expected
    objective, seen = recording(quadratic(TARGET))
    make(num_samples=100, num_elites=10, iterations=4).plan(objective, None, gen(0))
    assert [batch.shape[0] for batch in seen] == [100, 80, 64, 51]  # decay 1.25
    objective, seen = recording(quadratic(TARGET))
    make(num_samples=64, num_elites=8, iterations=3, decay=1.0).plan(objective, None, gen(0))
    assert [batch.shape[0] for batch in seen] == [64, 64, 64]


# ---------------------------------------------------------------------------- kept elites
HD, DT = 30, 0.1  # the smooth problem: a double integrator over 30 steps


def double_integrator_objective(smoothness: float = 1.0):
    """Drive p (nu=2, from rest at 0) to (1, -1) and stop there, with smooth actions.

    p_t = sum_{s<=t} v_s DT, v_t = sum_{s<=t} a_s DT. The return is -sum_t |p_t - p*|^2
    - 0.1 H |v_H|^2 - smoothness sum_t |a_t - a_(t-1)|^2; zero actions give -60.
    """
    target = torch.tensor([1.0, -1.0])

    def objective(actions: Tensor) -> Tensor:  # (N, H, 2) -> (N,)
        vel = torch.cumsum(actions * DT, dim=1)
        pos = torch.cumsum(vel * DT, dim=1)
        error = (pos - target.to(actions)).square().sum(dim=(1, 2))
        jerk = (actions[:, 1:] - actions[:, :-1]).square().sum(dim=(1, 2))
        return -error - 0.1 * HD * vel[:, -1].square().sum(-1) - smoothness * jerk

    return objective


def smooth_planner(**overrides: object) -> ICEMPlanner:
    kwargs = dict(
        num_samples=100,
        num_elites=10,
        iterations=4,
        beta=2.0,
        decay=1.25,
        keep_elites=0.3,
        init_std=0.5,
        min_std=0.05,
        momentum=0.1,
    )
    kwargs.update(overrides)
    return ICEMPlanner(HD, LOW, HIGH, **kwargs)


@pytest.mark.parametrize("seed", range(5))
def test_kept_elites_best_return_never_decreases(seed: int) -> None:
    objective, seen = recording(double_integrator_objective())
    planner = smooth_planner(iterations=6)
    result = planner.plan(objective, None, gen(seed))
    assert (result.iteration_best.diff() >= 0).all(), result.iteration_best
    assert planner.num_kept == 3  # ceil(0.3 * 10)
    # the kept elites lead the next population: the best 3 of the previous one
    for previous, batch in zip(seen[:-1], seen[1:], strict=True):
        returns = objective(previous)
        best = previous[torch.topk(returns, 3).indices]
        torch.testing.assert_close(batch[:3], best, atol=0, rtol=0)
    torch.testing.assert_close(result.elites[0], result.best_actions, atol=0, rtol=0)


def test_elites_warm_start_the_next_call() -> None:
    """The shifted elites of one call are evaluated in the next call's first iteration."""
    objective, seen = recording(quadratic(TARGET[:1].expand(H, NU)))  # time-invariant
    planner = make(iterations=4)
    first = planner.plan(objective, None, gen(0))
    assert first.elites.shape == (planner.num_kept, H, NU)
    warm = planner.shift_elites(first.elites, steps=1)
    torch.testing.assert_close(warm[:, :-1], first.elites[:, 1:], atol=0, rtol=0)
    torch.testing.assert_close(warm[:, -1], first.elites[:, -1], atol=0, rtol=0)  # repeat
    seen.clear()
    second = planner.plan(objective, planner.shift(first.mean), gen(1), init_elites=warm)
    torch.testing.assert_close(seen[0][: planner.num_kept], warm, atol=0, rtol=0)
    assert second.iteration_best[0] >= objective(warm[:1]).item()
    cold = planner.plan(objective, planner.shift(first.mean), gen(1))
    assert second.iteration_best[0] >= cold.iteration_best[0]


def test_no_kept_elites() -> None:
    objective, seen = recording(quadratic(TARGET))
    planner = make(keep_elites=0.0, iterations=3)
    result = planner.plan(objective, None, gen(0), init_elites=torch.zeros(2, H, NU))
    assert result.elites.shape == (0, H, NU) and planner.num_kept == 0
    assert (seen[0] != 0).any(dim=(1, 2)).all()  # the given elites were not used


# ---------------------------------------------------------------------------- iCEM vs CEM
SEEDS = range(8)


def mean_plan_return(planner: ICEMPlanner | CEMPlanner, objective) -> float:
    """Return of the executed plan (the mean), averaged over SEEDS."""
    returns = [objective(planner.plan(objective, None, gen(s)).mean[None]).item() for s in SEEDS]
    return sum(returns) / len(returns)


def test_icem_beats_cem_at_equal_samples_on_a_smooth_problem() -> None:
    """Measured (8 seeds): iCEM about -20.4, CEM about -28.1, iCEM with white noise about
    -29.1; zero actions give -60. iCEM evaluates 100 + 80 + 64 + 51 = 295 sequences, CEM
    4 x 74 = 296."""
    objective = double_integrator_objective()
    icem = smooth_planner()
    total = sum(icem.population(i) for i in range(icem.iterations))
    cem = CEMPlanner(
        HD,
        LOW,
        HIGH,
        num_samples=-(-total // 4),
        num_elites=10,
        iterations=4,
        init_std=0.5,
        min_std=0.05,
        momentum=0.1,
    )
    assert cem.num_samples * cem.iterations >= total == 295
    icem_return = mean_plan_return(icem, objective)
    cem_return = mean_plan_return(cem, objective)
    white_return = mean_plan_return(smooth_planner(beta=0.0), objective)
    assert icem_return > cem_return + 4.0, (icem_return, cem_return)
    assert icem_return > white_return + 4.0, (icem_return, white_return)  # the noise matters


# ---------------------------------------------------------------------------- the policy
def test_policy_drives_double_integrator_to_origin() -> None:
    """Closed loop on q' = q + dt qd, qd' = qd + dt a with reward -q^2 - 0.1 a^2."""
    model = DoubleIntegrator()
    planner = ICEMPlanner(
        15, [-1.0], [1.0], num_samples=64, num_elites=8, iterations=3, dtype=torch.float64
    )
    policy = PlannerPolicy(planner, model_objective_factory(model, EndlessQuadraticTask()))
    q, qd = torch.tensor([0.5], dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    for step in range(40):
        td = policy(TensorDict({keys.Q: q, keys.QD: qd}))
        action = td[keys.ACTION]
        assert action.abs().max() <= 1.0 and action.dtype == torch.float64
        if step == 0:
            assert action.item() < 0  # push towards the origin
        state = model.step(q, qd, action)
        q, qd = state.q, state.qd
    assert isinstance(policy.last_result.elites, Tensor)
    assert abs(q.item()) < 0.1 and abs(qd.item()) < 0.2, (q, qd)


def test_policy_in_real_env_rollout() -> None:
    env = make_real_env("pendulum", seed=0)
    planner = ICEMPlanner(8, [-1.0], [1.0], num_samples=32, num_elites=4, iterations=2)
    factory = model_objective_factory(DoubleIntegrator(), EndlessQuadraticTask())
    td = env.rollout(4, policy=PlannerPolicy(planner, factory, replan_every=2))
    action = td[keys.ACTION]
    assert action.shape == (4, 1) and action.dtype == env.action_spec.dtype
    assert (action.abs() <= 1).all()


# ---------------------------------------------------------------------------- config
def test_config_builds_icem() -> None:
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="config", overrides=["planner=icem", "env=pendulum"])
    validate_train_config(cfg)
    system = make_env_parts("pendulum").system
    planner = build_planner(cfg.planner, system, torch.float32)
    assert isinstance(planner, ICEMPlanner)
    assert planner.horizon == cfg.env.horizon and planner.beta == 2.0
    assert planner.min_samples == 50 and planner.num_kept == 8  # 2 * 25, ceil(0.3 * 25)
    assert [planner.population(i) for i in range(planner.iterations)] == [256, 204, 163, 131]


# ---------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("kwargs", "bad"),
    [
        (dict(beta=-1.0), "beta"),
        (dict(beta=float("nan")), "beta"),
        (dict(decay=0.5), "decay"),
        (dict(keep_elites=1.5), "keep_elites"),
        (dict(keep_elites=-0.1), "keep_elites"),
        (dict(min_samples=5), "min_samples"),
        (dict(min_samples=101), "min_samples"),
        (dict(num_elites=0), "num_elites"),
        (dict(num_elites=101), "num_elites"),
        (dict(momentum=1.0), "momentum"),
        (dict(min_std=-1.0), "min_std"),
        (dict(init_std=0.0), "init_std"),
        (dict(iterations=0), "iterations"),
        (dict(keep_elites=1.0, min_samples=10), "keep_elites"),
    ],
)
def test_validation(kwargs: dict, bad: str) -> None:
    args = dict(horizon=H, action_low=LOW, action_high=HIGH, num_samples=100, num_elites=10)
    args.update(kwargs)
    with pytest.raises(ValueError, match=bad):
        ICEMPlanner(**args)


def test_bad_elites_shape() -> None:
    planner = make(iterations=1)
    with pytest.raises(ValueError, match="init_elites"):
        planner.plan(quadratic(TARGET), None, gen(0), init_elites=torch.zeros(2, H + 1, NU))
    with pytest.raises(ValueError, match="elites"):
        planner.shift_elites(torch.zeros(H, NU))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_plans_on_cuda() -> None:
    generator = torch.Generator(device="cuda").manual_seed(0)
    result = make().plan(quadratic(TARGET.cuda()), None, generator)
    assert result.mean.is_cuda and result.elites.is_cuda
    assert (result.first_action.cpu() - TARGET[0]).abs().max() < TOL


def test_policy_carries_kept_elites_between_plans_and_through_checkpoints() -> None:
    """The policy hands iCEM its shifted elites at the next plan, and a reloaded policy too."""
    seen: list[int] = []

    def factory(q0, qd0):
        def objective(actions):
            seen.append(actions.shape[0])
            return -(actions - 0.3).square().sum(dim=(-1, -2))

        return objective

    planner = ICEMPlanner(
        horizon=6,
        action_low=[-1.0],
        action_high=[1.0],
        num_samples=40,
        num_elites=8,
        iterations=2,
        keep_elites=0.5,
    )
    policy = PlannerPolicy(planner, factory, seed=0)
    q, qd = torch.zeros(1), torch.zeros(1)
    policy.act(q, qd)
    assert "elites" in policy._carried and policy._carried["elites"].shape == (4, 6, 1)
    clone = PlannerPolicy(planner, factory, seed=0)
    clone.load_state_dict(policy.state_dict())
    torch.testing.assert_close(clone._carried["elites"], policy._carried["elites"])
    torch.testing.assert_close(clone.act(q, qd), policy.act(q, qd))
