"""Suite `planner` and the bench options that reach the suites. No timed assertions."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException

from mbrl_delan.accelerate import CompiledStep
from mbrl_delan.bench import build_options
from mbrl_delan.benchmarks import (
    PLANNER_MODELS,
    SUITE_NAMES,
    BenchSettings,
    TimingConfig,
    get_suite,
)
from mbrl_delan.benchmarks import planner as suite
from mbrl_delan.benchmarks.planner import (
    LatencyPredictor,
    PlannerGrid,
    Setting,
    _objective_factory,
    build_planner,
    grid_from_options,
    make_case,
    measure,
    model_steps_per_call,
    paired_ratio,
    planner_config,
    run_planner,
    time_plan,
    torchrl_model,
)
from mbrl_delan.benchmarks.records import BASE_FIELDS, RecordWriter, read_records
from mbrl_delan.conf.bench_schema import check_suite_keys
from mbrl_delan.conf.checks import CONFIGS, ConfigError

OPTS = BenchSettings(
    device=torch.device("cpu"),
    timing=TimingConfig(repeats=2, min_time_s=0.005, warmup=1),
    quick=True,
)


def bench_config(*overrides: str):
    with initialize_config_dir(str(CONFIGS / "bench"), version_base="1.3"):
        return compose("config", overrides=list(overrides))


# ---------------------------------------------------------------------------- options
def test_options_reach_the_suites() -> None:
    options, bench = build_options(
        bench_config(
            "suite=planner",
            "quick=true",
            "planners=[cem,icem]",
            "models=[pendulum_delan]",
            "num_samples=[32,64]",
            "horizons=[4]",
            "iterations=[2]",
            "torchrl=false",
        )
    )
    assert bench.quick and bench.timing.repeats == 3
    grid = grid_from_options(options, bench.quick)
    assert grid == PlannerGrid(
        models=("pendulum_delan",),
        planners=("cem", "icem"),
        num_samples=(32, 64),
        horizons=(4,),
        iterations=(2,),
        torchrl=False,
    )
    defaults, bench = build_options(bench_config("suite=planner"))
    assert not bench.quick and defaults.planners is None
    assert grid_from_options(defaults) == PlannerGrid()
    assert grid_from_options(defaults, quick=True) == PlannerGrid.quick()


def test_a_suite_takes_only_its_own_options() -> None:
    """Each suite's keys are its config group's: another suite's is refused when Hydra
    composes the config; the suite's own are typed by its schema."""
    with pytest.raises(ConfigCompositionException, match="n_samples"):
        bench_config("suite=planner", "n_samples=100")
    with pytest.raises(ConfigError, match="n_samples is not an option of suite planner; it is "
                       "an option of suite identify, identify_humanoid"):  # fmt: skip
        check_suite_keys(["suite=planner", "n_samples=100"], "delan")  # the entry point's line
    check_suite_keys(["suite=identify", "n_samples=100", "quick=true", "hydra.run.dir=x"], "delan")
    options, _ = build_options(bench_config("suite=identify", "n_samples=100", "max_epochs=3"))
    assert (options.n_samples, options.max_epochs) == (100, 3)
    for bad in ("n_samples=0", "max_epochs=1.5"):
        with pytest.raises(ConfigError, match=bad.split("=")[0]):
            build_options(bench_config("suite=identify", bad))
    for bad in ("nv=[0]", "nv=[]"):
        with pytest.raises(ConfigError, match="nv"):
            build_options(bench_config("suite=delan", bad))


@pytest.mark.parametrize(
    "override",
    [
        "planners=[ppo]",
        "models=[cartpole]",
        "num_samples=[0]",
        "horizons=[]",
        "rollout_threads=0",
        "repeats=1.5",  # a float for an integer key
        "max_memory_gb=0",
        "min_time_s=nan",
    ],
)
def test_bad_option_values_are_config_errors(override: str) -> None:
    name = override.split("=")[0]
    with pytest.raises(ConfigError, match=name):
        build_options(bench_config("suite=planner", override))


def test_suite_is_registered() -> None:
    assert "planner" in SUITE_NAMES and get_suite("planner") is suite.run_planner_suite


def test_cases_and_planners_are_the_loops() -> None:
    """The suite builds models and planners from the loop's config on the pendulum: the
    YAML's settings, the setting's N, H and iterations, num_elites capped at N."""
    delan, ensemble = (make_case(name, torch.device("cpu")) for name in PLANNER_MODELS[:3:2])
    assert (delan.model.integrator, delan.model.substeps, delan.particles) == ("euler", 2, 1)
    assert ensemble.particles == 5 and ensemble.model.ensemble_size == 5
    mppi = planner_config("mppi", Setting(64, 7, 3))
    assert (mppi.num_samples, mppi.horizon, mppi.iterations) == (64, 7, 3)
    assert (mppi.temperature, mppi.noise_std, mppi.smoothing) == (0.5, 0.5, 0.8)
    assert planner_config("icem", Setting(16, 5, 1)).num_elites == 16
    assert planner_config("icem", Setting(1024, 5, 1)).num_elites == 25


# ---------------------------------------------------------------------------- the grid
def test_grid_runs_cheapest_first_and_counts_model_steps() -> None:
    settings = PlannerGrid().settings()
    assert len(settings) == 12 and settings[0] == Setting(256, 15, 1)
    assert settings[-1] == Setting(4096, 30, 5)
    assert all(a.work <= b.work for a, b in zip(settings[:-1], settings[1:], strict=True))
    case = make_case("pendulum_ensemble", torch.device("cpu"))
    icem = build_planner("icem", Setting(100, 5, 3), case.system, torch.float32)
    assert model_steps_per_call(icem, 5) == (100 + 80 + 64) * 5 * 5
    small = build_planner("cem", Setting(8, 5, 1), case.system, torch.float32)
    assert small.num_elites == 8  # capped at N


def test_humanoid_case_has_humanoid_v5_sizes() -> None:
    case = make_case("humanoid_delan", torch.device("cpu"))
    system = case.system
    assert (system.nq, system.nv, system.nu) == (24, 23, 17)
    assert system.control_dt == pytest.approx(0.015)
    assert case.q0.shape == (24,) and case.qd0.shape == (23,)
    reward = case.task.reward(case.q0[None], case.qd0[None], torch.zeros(1, 17))
    assert reward.item() == pytest.approx(case.q0[2].item())  # root height, no control cost


# ---------------------------------------------------------------------------- timing
def counting_call():
    calls = []
    return calls, lambda: calls.append(1)


def test_slow_prediction_times_single_calls_within_the_budget() -> None:
    calls, call = counting_call()
    timing = time_plan(call, predicted=10.0, bench=replace(OPTS, max_call_s=5.0), sync=lambda: None)
    assert len(calls) == 1 and timing.repeats == 1 and timing.calls_per_measurement == 1
    calls.clear()
    timing = time_plan(call, predicted=1.0, bench=replace(OPTS, max_call_s=5.0), sync=lambda: None)
    assert len(calls) == 2 == timing.repeats  # min(repeats 2, floor(2.5 s / 1 s))


def test_fast_call_gets_an_untimed_call_then_time_call() -> None:
    calls, call = counting_call()
    timing = time_plan(call, predicted=0.0, bench=OPTS, sync=lambda: None)
    assert len(calls) > 1 + OPTS.timing.repeats and timing.calls_per_measurement > 1


def test_predicted_too_slow_is_skipped_and_errors_are_notes() -> None:
    predictor = LatencyPredictor()
    predictor.observe(Setting(10, 10, 1), 1.0)
    assert predictor.predict(Setting(20, 10, 2)) == pytest.approx(4.0)
    opts = replace(OPTS, max_call_s=3.0)
    built = []
    skipped = measure(lambda: built.append(1), Setting(20, 10, 2), predictor, opts, lambda: None)
    assert skipped.timing is None and "predicted 4.0 s > max_call_s" in skipped.note
    assert not built  # not even built

    def bad() -> None:
        raise ValueError("num_elites must be ...")

    failed = measure(bad, Setting(1, 1, 1), LatencyPredictor(), opts, lambda: None)
    assert failed.timing is None and failed.note.startswith("not run: num_elites")


# ---------------------------------------------------------------------------- the suite
def test_quick_suite_writes_every_figure(tmp_path: Path) -> None:
    grid = replace(PlannerGrid.quick(), num_samples=(16,), horizons=(3,))
    writer = RecordWriter(tmp_path / "planner.jsonl")
    for record in run_planner(grid, OPTS):
        writer.write(record)
    records = read_records(tmp_path / "planner.jsonl")
    plain = {m for m in PLANNER_MODELS if "_compiled" not in m and not m.endswith("_graph")}
    assert set(grid.models) == plain
    expected = {(f"{m}-mppi-n16-h3-i1", "plan_latency_ms") for m in grid.models}
    expected |= {
        (f"{m}-torchrl_mppi-n16-h3-i1", "torchrl_plan_latency_ms")
        for m in grid.models
        if m != "pendulum_oracle"
    }
    expected |= {(case, "realtime_factor") for case, _ in expected}
    assert {(r["case"], r["metric"]) for r in records} == expected
    for r in records:
        assert set(BASE_FIELDS) <= set(r) and r["suite"] == "planner", r
        assert isinstance(r["value"], float) and math.isfinite(r["value"]) and r["value"] > 0, r
        assert (r["num_samples"], r["horizon"], r["iterations"]) == (16, 3, 1)
    by_key = {(r["case"], r["metric"]): r for r in records}
    for case, metric in expected:
        if metric == "realtime_factor":
            continue
        latency, factor = by_key[case, metric], by_key[case, "realtime_factor"]
        assert factor["value"] == pytest.approx(1e3 * latency["control_dt_s"] / latency["value"])
    humanoid = by_key["humanoid_delan-mppi-n16-h3-i1", "plan_latency_ms"]
    assert humanoid["control_dt_s"] == pytest.approx(0.015) and humanoid["nv"] == 23
    ensemble = by_key["pendulum_ensemble-mppi-n16-h3-i1", "plan_latency_ms"]
    assert ensemble["particles"] == 5 and ensemble["model_steps_per_call"] == 16 * 5 * 3
    oracle = by_key["pendulum_oracle-mppi-n16-h3-i1", "plan_latency_ms"]
    assert oracle["dtype"] == "float64" and oracle["device"] == "cpu"
    torchrl = by_key["pendulum_delan-torchrl_mppi-n16-h3-i1", "torchrl_plan_latency_ms"]
    assert torchrl["implementation"] == "torchrl" and "no warm start" in torchrl["note"]
    assert isinstance(torchrl["action_finite"], bool)


def test_compiled_cases_compile_our_step_and_the_model_step() -> None:
    case = make_case("pendulum_delan_compiled", torch.device("cpu"))
    plain = make_case("pendulum_delan", torch.device("cpu"))
    assert case.compile and isinstance(torchrl_model(case), CompiledStep)
    assert not plain.compile and torchrl_model(plain) is plain.model
    assert _objective_factory(case, torch.device("cpu")).compile
    assert not _objective_factory(plain, torch.device("cpu")).compile


def test_a_compiling_call_is_timed_after_two_untimed_calls() -> None:
    seconds = iter([30.0, 0.5, 0.5, 0.5])  # the first call compiles for 30 s
    calls: list[float] = []
    clock = {"now": 0.0}

    def call() -> None:
        calls.append(1)
        clock["now"] += next(seconds)

    opts = replace(OPTS, max_call_s=5.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("mbrl_delan.benchmarks.planner.time.perf_counter", lambda: clock["now"])
        timing = time_plan(call, predicted=1.0, bench=opts, sync=lambda: None, compiles=True)
    # repeats from the warm 0.5 s: min(repeats 2, floor(2.5 s / 0.5 s)); the 30 s is not timed
    assert len(calls) == 2 + timing.repeats and timing.repeats == 2
    assert timing.seconds_per_call == pytest.approx(0.5)


# ---------------------------------------------------------------------------- paired
def test_paired_ratio_alternates_and_takes_the_median_of_the_rounds_ratios() -> None:
    """Round r: ours then TorchRL's (r even) or the reverse; a slow spell (x3) hits both."""

    def ours() -> None: ...

    def theirs() -> None: ...

    order: list[str] = []
    slow = {2, 3}  # the measurements in round 1 (the 3rd and 4th taken) are slowed down

    def seconds_per_call(call) -> float:
        order.append("ours" if call is ours else "theirs")
        base = 0.02 if call is ours else 0.08
        return base * (3.0 if len(order) - 1 in slow else 1.0)

    paired = paired_ratio(ours, theirs, rounds=3, seconds_per_call=seconds_per_call)
    assert order == ["ours", "theirs", "theirs", "ours", "ours", "theirs"]
    assert paired.ratio == pytest.approx(0.25)  # every round's ratio is 0.02 / 0.08
    assert paired.spread == pytest.approx(0.0)
    assert paired.ours_s == pytest.approx(0.02) and paired.theirs_s == pytest.approx(0.08)
    assert paired.rounds == 3


def test_paired_ratio_is_the_median_ratio_not_the_ratio_of_medians() -> None:
    def ours() -> None: ...

    def theirs() -> None: ...

    times = iter([1.0, 2.0, 4.0, 3.0, 1.0, 10.0])  # (ours, theirs): (1, 2), (3, 4), (1, 10)
    paired = paired_ratio(ours, theirs, rounds=3, seconds_per_call=lambda call: next(times))
    assert paired.ratio == pytest.approx(0.5)  # ratios 0.5, 0.75, 0.1
    assert paired.ours_s == pytest.approx(1.0) and paired.theirs_s == pytest.approx(4.0)
    assert paired.spread == pytest.approx((0.75 - 0.1) / 0.5)


def test_paired_records_time_ours_against_torchrl_on_the_eager_twin() -> None:
    grid = replace(
        PlannerGrid.quick(),
        models=("pendulum_delan",),
        num_samples=(16,),
        horizons=(3,),
        paired=True,
    )
    records = list(run_planner(grid, OPTS))
    paired = [r for r in records if r.metric == "latency_ratio_vs_torchrl"]
    assert [r.case for r in paired] == ["pendulum_delan-mppi_vs_torchrl-n16-h3-i1"]
    fields = paired[0].extra
    assert fields["torchrl_model"] == "pendulum_delan" and fields["repeats"] == 2
    assert fields["plan_latency_ms"] > 0 and fields["torchrl_plan_latency_ms"] > 0
    assert "no warm start" in fields["note"]
    assert paired[0].value > 0 and math.isfinite(paired[0].value)
