"""Suite `mocap` of `python -m mbrl_delan.bench`: every figure, its settings, missing clips.

No timed assertions: only that figures exist, are finite and positive.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from mbrl_delan.bench import run
from mbrl_delan.benchmarks import SUITE_NAMES, SuiteOptions, TimingConfig, get_suite
from mbrl_delan.benchmarks.mocap import (
    METRICS,
    MocapBenchConfig,
    run_mocap,
    run_mocap_suite,
)
from mbrl_delan.benchmarks.records import read_records
from mbrl_delan.data.mocap import humanoid_cmu_xml

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
MODELS = ("delan", "mlp", "ensemble")
OPTS = SuiteOptions(
    nv=(2,),
    batch=(4,),
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
    with initialize_config_dir(str(CONFIGS), version_base="1.3"):
        cfg = compose("bench", overrides=["suite=mocap", "quick=true", f"out={out}"])
    run(cfg)
    records = read_records(out)
    assert {r["metric"] for r in records} == set(METRICS)
    assert len(records) == 2 + len(MODELS)
    for r in records:
        assert r["suite"] == "mocap" and "note" not in r, r
        assert r["value"] is not None and math.isfinite(r["value"]) and r["value"] > 0, r
    fits = {r["model"]: r for r in records if r["metric"] == "fit_samples_per_s"}
    assert set(fits) == set(MODELS)
    for r in fits.values():
        assert r["batch_size"] == 16 and r["steps_per_epoch"] == math.ceil(r["train_samples"] / 16)
    retarget = next(r for r in records if r["metric"] == "retarget_frames_per_s")
    assert retarget["clips"] == ["09_06"] and retarget["frames"] == 141
    build = next(r for r in records if r["metric"] == "dataset_build_s")
    assert build["samples"] == 64


def test_missing_clips_give_null_records_with_a_note(humanoid, tmp_path: Path) -> None:
    cfg = replace(MocapBenchConfig.quick(), clips=("09_77",), folders=(str(tmp_path),))
    records = list(run_mocap(cfg, OPTS))
    assert {r.metric for r in records} == set(METRICS) and len(records) == 2 + len(MODELS)
    for r in records:
        assert r.value is None and "09_77" in r.extra["note"]


def test_settings_are_the_fit_configs_defaults() -> None:
    """The suite builds data and models as configs/fit says (a copy, kept equal here)."""
    bench = MocapBenchConfig()
    top = OmegaConf.load(CONFIGS / "fit" / "config.yaml")
    assert (bench.batch_size, bench.lr, bench.max_grad_norm, bench.std_floor) == (
        top.batch_size,
        top.lr,
        top.max_grad_norm,
        top.loss.std_floor,
    )
    assert bench.translation_invariant == top.translation_invariant
    assert top.lr_schedule == "constant"  # the timed epoch has no schedule
    assert str(bench.dtype) == f"torch.{top.dtype}"
    data = OmegaConf.load(CONFIGS / "fit" / "data" / "cmu_mocap.yaml")
    assert list(bench.clips) == list(data.clips)
    assert list(bench.val_clips) == list(data.val_clips)
    assert list(bench.folders) == list(data.folders)
    assert bench.samples_per_clip == data.samples_per_clip
    filt = bench.filter
    assert (filt.cutoff_hz, filt.order, filt.edge_trim_s) == tuple(
        data.filter[k] for k in ("cutoff_hz", "order", "edge_trim_s")
    )
    assert (bench.val_time_fraction, bench.gap_s, bench.split_seed) == tuple(
        data.split[k] for k in ("val_time_fraction", "gap_s", "seed")
    )
    assert (bench.glitch_deg, bench.glitch_pad_s) == (data.glitch.deg, data.glitch.pad_s)
    assert bench.passive == data.passive and data.torques == "inverse"
    for name in MODELS:
        model = OmegaConf.load(CONFIGS / "fit" / "model" / f"{name}.yaml")
        prefix = {"delan": "delan_", "mlp": "mlp_", "ensemble": "ensemble_"}[name]
        for key, value in model.items():
            if key == "name":
                continue
            attr = key if key == "ensemble_size" else prefix + key
            assert getattr(bench, attr) == value, (name, key)
