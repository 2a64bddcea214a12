"""Suite `own_arm` of `python -m mbrl_delan.bench`: the benchmark contract's metrics and
fields, its choices checked, and its sample-efficiency figure. No timed assertions."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from mbrl_delan.bench import build_options, run
from mbrl_delan.benchmarks import OWN_ARM_ROBOTS, SUITE_NAMES, get_suite
from mbrl_delan.benchmarks.own_arm import main, run_own_arm_suite, sample_curves
from mbrl_delan.benchmarks.records import read_records
from mbrl_delan.conf.checks import CONFIGS, ConfigError
from mbrl_delan.systems.arms import ARMS


def _bench(overrides: list[str]):
    with initialize_config_dir(str(CONFIGS / "bench"), version_base="1.3"):
        return compose("config", overrides=["suite=own_arm", *overrides])


def test_suite_is_registered_with_the_shipped_arms() -> None:
    assert "own_arm" in SUITE_NAMES and get_suite("own_arm") is run_own_arm_suite
    assert OWN_ARM_ROBOTS == tuple(ARMS)


def test_quick_run_writes_the_contracts_records_and_its_figure(tmp_path: Path) -> None:
    out = tmp_path / "own_arm.jsonl"
    run(_bench(["quick=true", "models=[white_box,mlp]", "samples=[400,800]", f"out={out}"]))
    records = read_records(out)
    by_model: dict[str, set[str]] = {}
    for r in records:
        assert r["suite"] == "own_arm" and r["robot"] == "panda" and r["friction"] == "none"
        assert r["seed"] == 0 and r["samples"] in (400, 800)
        assert r["train_design"] == r["test_design"] == "fourier"
        assert r["value"] is not None and math.isfinite(r["value"]), r
        by_model.setdefault(r["model"], set()).add(r["metric"])
    common = {"test_torque_r2", "val_torque_r2", "test_torque_mse", "fit_wall_s", "truth_torque_r2"}
    assert by_model["white_box"] == common | {"mass_matrix_error", "friction_torque_share"}
    assert by_model["mlp"] == common | {"fit_epoch_s"}
    box = [r for r in records if r["model"] == "white_box" and r["metric"] == "test_torque_r2"]
    assert min(r["value"] for r in box) > 0.99  # identified from a few hundred samples
    curves = sample_curves(records, "panda", "none")
    assert [n for n, _ in curves["white_box"]] == [400, 800]
    assert main([str(out), "--out", str(tmp_path / "fig.png")]) == 0
    assert (tmp_path / "fig.png").stat().st_size > 0
    assert main([str(out), "--out", str(tmp_path / "f.png"), "--robot", "ur5e"]) == 2


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("models=[delan,gp]", "models=.*delan, mlp, white_box"),
        ("robots=[ur10]", "robots"),
        ("samples=[]", "samples=\\[\\] is not valid"),
        ("friction=[true]", "friction"),
        ("designs=[chirp]", "designs"),
    ],
)
def test_bad_choices_are_config_errors(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        build_options(_bench([override]))


def test_a_cross_design_case_tests_on_the_other_designs_trajectories(tmp_path: Path) -> None:
    """Trained on point-to-point moves, tested on Fourier trajectories of their own seed;
    the white box on Coulomb + viscous data identifies the law it was made with."""
    out = tmp_path / "cross.jsonl"
    run(_bench(["quick=true", "models=[white_box]", "friction=[coulomb_viscous]", "samples=[3000]",
                "designs=[point_to_point]", "test_designs=[fourier]", f"out={out}"]))  # fmt: skip
    records = read_records(out)
    assert {r["case"] for r in records} == {
        "panda_white_box_coulomb_viscous_3000_point_to_point_to_fourier"}  # fmt: skip
    r2 = {r["metric"]: r["value"] for r in records}
    assert r2["test_torque_r2"] > 0.99 and r2["val_torque_r2"] > 0.99
    assert r2["truth_torque_r2"] > r2["test_torque_r2"] - 1e-3  # the arm's own: the ceiling
    assert all(r["train_design"] == "point_to_point" and r["test_design"] == "fourier"
               for r in records)  # fmt: skip
