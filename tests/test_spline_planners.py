"""Spline action sequences (knots + interpolation) and predictive sampling, on worked answers."""

from __future__ import annotations

import pytest
import torch

from mbrl_delan.planners import (
    CEMPlanner,
    ICEMPlanner,
    KnotSpline,
    MPPIPlanner,
    PlannerPolicy,
    PredictiveSampling,
)
from mbrl_delan.planners.spline import knot_steps

H, NU = 13, 2
LOW, HIGH = [-1.0, -1.0], [1.0, 1.0]
T = torch.arange(H, dtype=torch.float64)
# a target each interpolation holds exactly with 4 knots at steps 0, 4, 8, 12: a ramp
RAMP = torch.stack([0.1 * T - 0.6, -0.05 * T + 0.3], dim=-1)  # (H, nu)


def quadratic(target: torch.Tensor):
    """returns = -sum_t |a_t - target_t|^2: the optimum is the target."""
    return lambda actions: -(actions - target.to(actions)).square().sum(dim=(1, 2))


def test_knots_are_spread_over_the_horizon_and_read_back() -> None:
    assert knot_steps(13, 4).tolist() == [0, 4, 8, 12]
    assert knot_steps(10, 3).tolist() == [0, 4, 9]  # 4.5 rounds to even
    for kind in ("zero", "linear", "cubic"):
        spline = KnotSpline(H, 4, kind)
        knots = torch.randn(5, 4, NU, dtype=torch.float64)
        actions = spline.actions(knots)
        assert actions.shape == (5, H, NU)
        torch.testing.assert_close(spline.knots_of(actions), knots)  # interpolating


def test_interpolations_have_their_worked_values() -> None:
    knots = torch.tensor([[0.0], [1.0], [3.0], [2.0]], dtype=torch.float64)  # at 0, 4, 8, 12
    hold = KnotSpline(H, 4, "zero").actions(knots)[:, 0]
    assert hold.tolist() == [0.0] * 4 + [1.0] * 4 + [3.0] * 4 + [2.0]
    line = KnotSpline(H, 4, "linear").actions(knots)[:, 0]
    torch.testing.assert_close(line[:5], torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0]).double())
    torch.testing.assert_close(line[6], torch.tensor(2.0).double())
    ramp = torch.stack([T[[0, 4, 8, 12]]], dim=-1)  # a straight line: every kind keeps it
    for kind in ("linear", "cubic"):
        torch.testing.assert_close(KnotSpline(H, 4, kind).actions(ramp), T[:, None])
    # cubic with centred slopes on evenly spaced knots reproduces a quadratic between the
    # inner knots (its finite-difference slopes are exact there)
    spline = KnotSpline(17, 5, "cubic")  # knots at 0, 4, 8, 12, 16
    t = torch.arange(17, dtype=torch.float64)
    quad = (0.1 * t**2)[:, None]
    torch.testing.assert_close(spline.actions(spline.knots_of(quad))[4:13], quad[4:13])


def test_every_step_a_knot_is_the_plain_planner() -> None:
    """knots = None or H: the same samples, plans and returns as without a spline."""
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    plain = MPPIPlanner(H, LOW, HIGH, num_samples=64, iterations=3, noise_std=0.3)
    knotted = MPPIPlanner(H, LOW, HIGH, num_samples=64, iterations=3, noise_std=0.3, knots=H)
    a = plain.plan(quadratic(RAMP), None, g1)
    b = knotted.plan(quadratic(RAMP), None, g2)
    torch.testing.assert_close(a.mean, b.mean)
    torch.testing.assert_close(a.iteration_best, b.iteration_best)


@pytest.mark.parametrize(
    "planner",
    [
        MPPIPlanner(H, LOW, HIGH, num_samples=256, iterations=20, temperature=0.05,
                    noise_std=0.2, knots=4, interpolation="linear"),
        CEMPlanner(H, LOW, HIGH, num_samples=256, num_elites=25, iterations=12, knots=4,
                   interpolation="cubic"),
        ICEMPlanner(H, LOW, HIGH, num_samples=256, num_elites=25, iterations=8, knots=4,
                    interpolation="linear"),
        PredictiveSampling(H, LOW, HIGH, num_samples=32, iterations=60, noise_std=0.1,
                           knots=4, interpolation="linear"),
    ],
    ids=["mppi", "cem", "icem", "predictive"],
)  # fmt: skip
def test_planners_over_four_knots_find_a_ramp(planner) -> None:
    """The ramp is a 4-knot spline: each planner finds it, searching 8 numbers, not 26
    (from zeros, 0.6 away; seeds 0-3 ended within 0.002 (CEM) to 0.08 (predictive))."""
    result = planner.plan(quadratic(RAMP), None, torch.Generator().manual_seed(0))
    assert result.mean.shape == (H, NU)
    assert (result.mean - RAMP.float()).abs().max() < 0.15


def test_predictive_sampling_never_loses_its_nominal() -> None:
    """The nominal plan is among the samples, so the best return never falls."""
    planner = PredictiveSampling(H, LOW, HIGH, num_samples=8, iterations=30, knots=3)
    result = planner.plan(quadratic(RAMP), None, torch.Generator().manual_seed(1))
    best = result.iteration_best
    assert bool((best[1:] >= best[:-1]).all()) and float(best[-1]) > float(best[0])


def test_warm_start_is_the_previous_spline_at_the_shifted_knot_times() -> None:
    """The policy shifts the plan by the steps executed; the next plan's first knots are the
    previous plan read at the shifted knot steps (here, with no iteration's change, exactly)."""
    planner = CEMPlanner(H, LOW, HIGH, num_samples=4, num_elites=2, iterations=1, knots=4)
    previous = planner.spline.actions(torch.tensor([[0.0, 0.1], [0.4, 0.2], [0.8, -0.2],
                                                    [0.5, 0.0]]))  # fmt: skip
    shifted = planner.shift(previous, 2)
    knots = planner.spline.knots_of(shifted)
    expected = previous[[2, 6, 10, 12]]  # steps 0, 4, 8, 12 read 2 later (the end held)
    torch.testing.assert_close(knots, expected)


def test_policy_over_a_spline_planner_returns_actions_of_every_step() -> None:
    planner = MPPIPlanner(H, LOW, HIGH, num_samples=32, iterations=2, knots=3, noise_std=0.2)
    policy = PlannerPolicy(planner, lambda q, qd: quadratic(RAMP))
    action = policy.act(torch.zeros(1), torch.zeros(1))
    assert action.shape == (NU,) and policy.plan_mean.shape == (H, NU)
    policy.act(torch.zeros(1), torch.zeros(1))  # warm-started from the shifted plan


def test_bad_spline_settings_are_named() -> None:
    with pytest.raises(ValueError, match="knots must be in"):
        MPPIPlanner(H, LOW, HIGH, knots=H + 1)
    with pytest.raises(ValueError, match="interpolation must be one of"):
        CEMPlanner(H, LOW, HIGH, knots=3, interpolation="quintic")
    with pytest.raises(ValueError, match="needs knots >= 2"):
        CEMPlanner(H, LOW, HIGH, knots=1, interpolation="cubic")
