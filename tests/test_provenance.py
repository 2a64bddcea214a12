"""Where a figure comes from (`mbrl_delan.provenance`): the command as typed, the code's
commit and the host, in bench records and run summaries."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from mbrl_delan import provenance as prov
from mbrl_delan.bench import run
from mbrl_delan.benchmarks.records import read_records
from tests.test_own_arm import _bench


def test_the_command_is_the_console_script_or_python_m_and_none_from_python(monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["/venv/bin/mbrl-delan-bench", "suite=own_arm",
                                      "models=[tree_delan, mlp]"])  # fmt: skip
    assert prov.command_line("mbrl_delan.bench") == (
        "mbrl-delan-bench suite=own_arm 'models=[tree_delan, mlp]'")  # fmt: skip
    monkeypatch.setattr(sys, "argv", [str(prov.PACKAGE_DIR / "fit.py"), "data=excitation"])
    assert prov.command_line("mbrl_delan.fit") == "python -m mbrl_delan.fit data=excitation"
    assert prov.command_line("mbrl_delan.train") is None  # fit.py is not the train command
    monkeypatch.setattr(sys, "argv", ["/usr/bin/pytest", "-q"])
    assert prov.command_line("mbrl_delan.bench") is None


def test_the_commit_is_the_checkouts_and_dirty_says_whether_it_changed() -> None:
    version = prov.code_version()
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=prov.PACKAGE_DIR, capture_output=True,
                          text=True, check=False)  # fmt: skip
    if head.returncode != 0:
        pytest.skip("the package is not in a git checkout here")
    assert version["git_commit"] == head.stdout.strip()
    assert isinstance(version["dirty"], bool)


def test_bench_records_carry_the_command_the_commit_and_the_host(tmp_path: Path) -> None:
    out = tmp_path / "own_arm.jsonl"
    run(_bench(["quick=true", "models=[white_box]", f"out={out}"]))
    for record in read_records(out):
        assert record["command"] is None  # called from Python, not the bench's command line
        assert record["git_commit"] is None or re.fullmatch("[0-9a-f]{40}", record["git_commit"])
        host = record["host"]
        assert host["cpus"] >= 1 and host["threads"] >= 1 and host["load_1min"] >= 0
        assert host["cpu"]


def test_a_fits_summary_names_where_it_comes_from(tmp_path: Path) -> None:
    from mbrl_delan.conf.checks import compose_config
    from mbrl_delan.conf.fitting import FIT_CONFIG_DIR
    from mbrl_delan.fit_run import _run

    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=600", "model=white_box",
                 "logger=none", "threads=1"]  # fmt: skip
    _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert {"command", "git_commit", "dirty", "host"} <= set(summary)
    assert summary["host"]["threads"] >= 1


def test_every_kept_bench_record_says_where_it_comes_from() -> None:
    """The bench records under docs/records/ carry the provenance keys, null where the
    record predates them (what made it is then unknown, and says so); a loop's are in its
    summary.json."""
    records = Path(__file__).resolve().parents[1] / "docs" / "records"
    for path in sorted({*records.glob("*.jsonl"), *records.glob("own_arm/*.jsonl")}):
        for record in read_records(path):
            assert {"command", "git_commit", "dirty", "host"} <= set(record), path


def test_the_kept_stand_oracles_are_the_episodes_every_loop_of_their_seed_met() -> None:
    """docs/records/oracles/humanoid_stand/n32h30_s<seed>/oracle.json (the default preset's
    oracle, evaluated on its own) holds, to the last digit, the oracle episodes of the final
    paired evaluation of every kept humanoid_stand loop of that seed at that preset."""
    records = Path(__file__).resolve().parents[1] / "docs" / "records"
    oracles = sorted((records / "oracles" / "humanoid_stand").glob("n32h30_s*/oracle.json"))
    assert oracles
    for path in oracles:
        oracle = json.loads(path.read_text())
        seed = path.parent.name.removeprefix("n32h30_s")
        runs = sorted((records / "loops" / "humanoid_stand").glob(f"*_n32h30*_s{seed}"))
        assert runs, path
        for loop in runs:
            lines = (loop / "metrics.jsonl").read_text().splitlines()
            paired = [r for r in map(json.loads, lines) if "oracle_episode_steps" in r][-1]
            assert paired["oracle_episode_steps"] == oracle["steps"], loop
            assert paired["oracle_episode_returns"] == oracle["returns"], loop
