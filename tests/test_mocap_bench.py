"""Suite `mocap` of `python -m mbrl_delan.bench`: every figure, its settings, missing clips.

No timed assertions: only that figures exist, are finite and positive.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from mbrl_delan.bench import run
from mbrl_delan.benchmarks import SUITE_NAMES, BenchSettings, TimingConfig, get_suite
from mbrl_delan.benchmarks.mocap import (
    METRICS,
    QUICK_OVERRIDES,
    mocap_config,
    run_mocap,
    run_mocap_suite,
)
from mbrl_delan.benchmarks.records import read_records
from mbrl_delan.conf.checks import CONFIGS
from mbrl_delan.data.mocap import humanoid_cmu_xml

MODELS = ("delan", "mlp", "ensemble")
OPTS = BenchSettings(
    device=torch.device("cpu"),
    timing=TimingConfig(repeats=2, min_time_s=0.005, warmup=1),
    quick=True,
)


@pytest.fixture(scope="module")
def humanoid() -> None:
    try:
        humanoid_cmu_xml()
    except (ModuleNotFoundError, FileNotFoundError) as err:
        pytest.skip(f"humanoid_CMU.xml unavailable: {err}")


def test_suite_is_registered() -> None:
    assert "mocap" in SUITE_NAMES and get_suite("mocap") is run_mocap_suite


def test_quick_run_writes_every_metric(humanoid, tmp_path: Path) -> None:
    out = tmp_path / "mocap.jsonl"
    with initialize_config_dir(str(CONFIGS / "bench"), version_base="1.3"):
        cfg = compose("config", overrides=["suite=mocap", "quick=true", f"out={out}"])
    run(cfg)
    records = read_records(out)
    assert {r["metric"] for r in records} == set(METRICS)
    assert len(records) == 2 + 2 * len(MODELS)
    for r in records:
        assert r["suite"] == "mocap" and "note" not in r, r
        assert r["value"] is not None and math.isfinite(r["value"]) and r["value"] > 0, r
    fits = {r["model"]: r for r in records if r["metric"] == "fit_samples_per_s"}
    assert set(fits) == set(MODELS)
    for r in fits.values():
        assert r["batch_size"] == 16 and r["steps_per_epoch"] == math.ceil(r["train_samples"] / 16)
    epochs = {r["model"]: r for r in records if r["metric"] == "fit_epoch_s"}
    for name, r in epochs.items():  # one timing, two figures
        assert r["value"] * fits[name]["value"] == pytest.approx(r["train_samples"])
    retarget = next(r for r in records if r["metric"] == "retarget_frames_per_s")
    assert retarget["clips"] == ["09_06"] and retarget["frames"] == 141
    build = next(r for r in records if r["metric"] == "dataset_build_s")
    assert build["samples"] == 64


def test_missing_clips_give_null_records_with_a_note(humanoid, tmp_path: Path) -> None:
    cfg = mocap_config([*QUICK_OVERRIDES, "data.clips=['09_77']", f"data.folders=['{tmp_path}']"])
    records = list(run_mocap(cfg, OPTS))
    assert {r.metric for r in records} == set(METRICS) and len(records) == 2 + 2 * len(MODELS)
    for r in records:
        assert r.value is None and "09_77" in r.extra["note"]


def test_the_suite_runs_the_fits_own_settings() -> None:
    """The suite's data, training and model settings are those ``python -m mbrl_delan.fit``
    composes (with the quick run's overrides where given), built by the fit's builders."""
    bench = mocap_config()
    assert (bench.fit.batch_size, bench.fit.lr, bench.fit.lr_schedule) == (256, 0.001, "constant")
    assert len(bench.clips) == 15 and bench.dtype == torch.float32
    assert (bench.models["delan"].hidden, bench.models["ensemble"].ensemble_size) == (128, 5)
    quick = mocap_config(QUICK_OVERRIDES)
    assert quick.clips == ["09_06"] and quick.fit.batch_size == 16
    assert quick.models["mlp"].hidden == 16 and quick.models["ensemble"].ensemble_size == 2
    assert quick.resolved_folders() == [(Path(__file__).parent / "data").resolve()]
