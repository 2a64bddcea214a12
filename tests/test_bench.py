"""`python -m mbrl_delan.bench`: the JSONL it writes, the naive reference, FLOP counts, errors.

No timed assertions here: only that figures exist, are finite and positive.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import pytest
import torch
from hydra import compose, initialize_config_dir

from mbrl_delan.bench import run
from mbrl_delan.benchmarks import (
    SUITE_NAMES,
    BenchSettings,
    TimingConfig,
    UnknownSuiteError,
    get_suite,
)
from mbrl_delan.benchmarks import delan as delan_suite
from mbrl_delan.benchmarks.delan import (
    _fwd,
    _measure,
    _predict_call_s,
    _record,
    chain_mjcf,
    chain_model,
    forward_dynamics_flops,
    humanoid_cmu_path,
    model_flops,
    mujoco_system,
    naive_forward_dynamics,
    random_inputs,
)
from mbrl_delan.benchmarks.records import (
    BASE_FIELDS,
    BenchRecord,
    RecordWriter,
    format_table,
    read_records,
)
from mbrl_delan.conf.checks import CONFIGS, ConfigError

METRICS = (
    "fwd_dyn_per_s",
    "inv_dyn_per_s",
    "train_samples_per_s",
    "naive_fwd_dyn_per_s",
    "flops_fraction",
    "mujoco_fwd_per_s",
    "mujoco_rollout_steps_per_s",
    "matmul_flops_per_s",
)


def bench(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "mbrl_delan.bench",
        f"hydra.run.dir={tmp_path / 'run'}",
        "threads=1",
        *overrides,
    ]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)


def test_quick_cli_writes_every_metric(tmp_path: Path) -> None:
    out = tmp_path / "bench.jsonl"
    done = bench(tmp_path, "suite=delan", "quick=true", f"out={out}")
    assert done.returncode == 0, done.stdout + done.stderr
    records = read_records(out)
    assert {r["metric"] for r in records} == set(METRICS)
    for r in records:
        assert set(BASE_FIELDS) <= set(r), r
        assert r["suite"] == "delan"
        assert isinstance(r["value"], float) and math.isfinite(r["value"]) and r["value"] > 0, r
        assert r["threads"] == 1 and "torch_version" in r and "cpu" in r
    model_records = [r for r in records if r["metric"] in METRICS[:5]]
    assert all(r["nv"] == 2 and r["batch"] == 4 and r["dtype"] == "float32" for r in model_records)
    fraction = next(r for r in records if r["metric"] == "flops_fraction")
    assert 0.0 < fraction["value"] < 1.0 and fraction["flops_per_sample"] > 0
    assert "flops_fraction" in (tmp_path / "run" / "bench.log").read_text()  # the logged table


def test_records_are_appended_not_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "r.jsonl"
    for k in range(2):
        writer = RecordWriter(path)
        writer.write(BenchRecord("s", f"c{k}", "m", 1.5, "u", "cpu", {"nv": k}))
        writer.write(BenchRecord("s", f"c{k}", "m2", None, "u", "cpu", {"note": "skipped: x"}))
    records = read_records(path)
    assert [r["case"] for r in records] == ["c0", "c0", "c1", "c1"]
    assert records[1]["value"] is None and records[1]["note"] == "skipped: x"
    assert records[0]["nv"] == 0 and list(records[0])[:6] == list(BASE_FIELDS)
    assert "skipped: x" in format_table(writer.records)


@pytest.mark.parametrize("where", ["under_a_file", "a_folder"])
def test_an_out_that_cannot_be_written_fails_before_measuring(tmp_path: Path, where: str) -> None:
    """A bad `out=` is named at start, not as a traceback after the first measurement, and
    whatever is already there is left as it was."""
    blocker = tmp_path / "records.jsonl"
    blocker.write_text('{"kept": 1}\n')
    out = blocker / "x.jsonl" if where == "under_a_file" else tmp_path
    configs = str(CONFIGS / "bench")
    with initialize_config_dir(config_dir=configs, version_base=None):
        cfg = compose(config_name="config", overrides=["suite=planner", "quick=true", f"out={out}"])
    with pytest.raises(ConfigError, match="cannot append records there"):
        run(cfg)
    assert blocker.read_text() == '{"kept": 1}\n'


def test_record_rejects_non_finite_values_and_clashing_fields() -> None:
    with pytest.raises(ValueError, match="not finite"):
        BenchRecord("s", "c", "m", float("nan"), "u", "cpu").to_dict()
    with pytest.raises(ValueError, match="base field"):
        BenchRecord("s", "c", "m", 1.0, "u", "cpu", {"value": 2.0}).to_dict()


@pytest.mark.parametrize("nv", [2, 3])
def test_naive_reference_matches_delan_forward_dynamics(nv: int) -> None:
    """The naive comparison computes the same function as ours (float64, 1e-8)."""
    model = chain_model(nv, seed=nv).double()
    with torch.no_grad():  # random biases and friction: no symmetry of the init helps
        for layer in model.modules():
            if isinstance(layer, torch.nn.Linear):
                layer.bias.normal_(0.0, 0.5)
        model.dynamics.dissipation.raw_viscous.normal_()
        model.dynamics.dissipation.raw_coulomb.normal_()
    x = random_inputs(nv, 32, torch.device("cpu"), dtype=torch.float64, seed=1)
    ours = model.dynamics.forward_dynamics(x.q, x.qd, x.tau)
    with torch.inference_mode():
        naive = naive_forward_dynamics(model, x.q, x.qd, x.tau)
    assert ours.abs().max() > 1e-2  # not trivially zero
    torch.testing.assert_close(naive, ours, rtol=1e-8, atol=1e-8)


def test_flop_count_is_positive_and_grows_with_nv() -> None:
    counts = [forward_dynamics_flops(nv, 2 * nv, 64, 2) for nv in (1, 2, 7, 23, 62)]
    assert counts[0] > 0
    assert all(a < b for a, b in zip(counts[:-1], counts[1:], strict=True))
    # nv=2: f=4, o=4; one pass 2 (4*64 + 64*64 + 64*4) = 9216; 3 passes + 11*4.
    assert forward_dynamics_flops(2, 4, 64, 2) == 3 * 9216 + 44
    assert model_flops(chain_model(2)) == forward_dynamics_flops(2, 4, 64, 2)


def test_every_suite_has_a_function_and_a_schema() -> None:
    """The suites' functions (benchmarks) and their options' schemas (conf) name the same
    suites, and each function imports."""
    from mbrl_delan.benchmarks import SUITES

    assert tuple(SUITES) == SUITE_NAMES
    assert all(callable(get_suite(name)) for name in SUITE_NAMES)


def test_unknown_suite_names_the_valid_ones(tmp_path: Path) -> None:
    with pytest.raises(UnknownSuiteError, match="delan"):
        get_suite("nope")
    assert "delan" in SUITE_NAMES and callable(get_suite("delan"))
    done = bench(tmp_path, "suite=nope")
    assert done.returncode == 2
    assert "nope" in done.stderr + done.stdout and "delan" in done.stderr + done.stdout


def test_too_slow_figure_is_recorded_as_skipped_with_a_note() -> None:
    opts = BenchSettings(
        device=torch.device("cpu"),
        timing=TimingConfig(repeats=1, min_time_s=1e-3, warmup=0),
        max_call_s=1e-9,
    )
    model = chain_model(2)
    x = random_inputs(2, 32, opts.device)
    measured = _measure(_fwd(model), x, opts, lambda: None)
    record = _record("c", "fwd_dyn_per_s", "evals/s", "cpu", {}, measured, 32)
    assert record.value is None and record.extra["note"].startswith("skipped")
    assert json.loads(json.dumps(record.to_dict()))["value"] is None


def test_call_time_prediction_retries_at_larger_trial_batches(monkeypatch) -> None:
    """Fixed overhead makes a batch-16 trial pessimistic; a batch-128 trial corrects it."""
    trials: list[int] = []

    def fake_seconds(call, sync) -> float:
        trials.append(call())
        return 0.01 + 1e-4 * trials[-1]  # 10 ms overhead + 0.1 ms per sample

    monkeypatch.setattr(delan_suite, "single_call_seconds", fake_seconds)
    x = random_inputs(2, 4096, torch.device("cpu"))

    def make(inputs):
        return lambda: inputs.batch

    assert _predict_call_s(make, x, 1.0, lambda: None) == pytest.approx(0.0228 * 32)
    assert trials == [16, 128]
    trials.clear()  # the batch-128 trial itself would take too long: stop at the first one
    assert _predict_call_s(make, x, 0.05, lambda: None) == pytest.approx(0.0116 * 256)
    assert trials == [16]
    assert _predict_call_s(make, x.head(16), 1e-9, lambda: None) == 0.0


@pytest.mark.parametrize("nv", [1, 2, 7])
def test_mujoco_chain_has_nv_hinges_and_no_contacts(nv: int) -> None:
    model = mujoco.MjModel.from_xml_string(chain_mjcf(nv))
    assert model.nv == model.nq == model.nu == nv
    assert model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    system = mujoco_system(nv)
    assert system.name == "chain" and system.model.nv == nv


def test_nv62_uses_the_cmu_humanoid_when_dm_control_is_there() -> None:
    system = mujoco_system(62)
    assert system.model.nv == 62
    assert system.model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    if humanoid_cmu_path() is None:
        assert system.name == "chain" and "dm_control" in system.note
    else:
        assert system.name == "humanoid_CMU"
    assert mujoco_system(62, humanoid=False).name == "chain"


def test_soak_suite_records_memory_and_time_per_round(tmp_path: Path) -> None:
    """suite=soak (quick: 3 rounds of the pendulum loop): rss_mb and round_s for each round,
    in order, and the memory growth over the second half."""
    out = tmp_path / "soak.jsonl"
    done = bench(tmp_path, "suite=soak", "quick=true", f"out={out}")
    assert done.returncode == 0, done.stdout + done.stderr
    records = read_records(out)
    for metric, unit in (("rss_mb", "MB"), ("round_s", "s")):
        rows = [r for r in records if r["metric"] == metric]
        assert [r["round"] for r in rows] == [1, 2, 3] and {r["unit"] for r in rows} == {unit}
        assert all(r["value"] > 0 for r in rows)
        assert [r["env_steps"] for r in rows] == sorted(r["env_steps"] for r in rows)
    rss = [r["value"] for r in records if r["metric"] == "rss_mb"]
    (growth,) = [r for r in records if r["metric"] == "rss_growth_mb"]
    assert growth["value"] == pytest.approx(rss[-1] - rss[0]) and growth["from_round"] == 1
