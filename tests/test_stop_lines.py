"""Every entry point ends a run it cannot do with one line ``<kind>: <what>`` on standard
error (exit 2), once, and nothing of it on standard output (`mbrl_delan.stops`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _cases(tmp: Path) -> dict[str, tuple[list[str], str]]:
    garbage = tmp / "cut.npz"
    garbage.write_bytes(b"PK\x03\x04 not a whole archive")
    return {
        "train": (["mbrl_delan.train", "planner.num_samples=-1"], "config error"),
        "fit": (
            [
                "mbrl_delan.fit",
                "data=arrays",
                f"data.path={garbage}",
                "data.mjcf=arm2",
                f"hydra.run.dir={tmp / 'fit'}",
                "logger=none",
            ],
            "bad data file",
        ),  # fmt: skip
        "bench": (["mbrl_delan.bench", "suite=nope"], "config error"),
        "evaluate": (["mbrl_delan.evaluate", str(tmp / "no_run")], "not found"),
        "report": (["mbrl_delan.report", str(tmp / "no_runs")], "not a folder"),
    }


@pytest.mark.parametrize("entry", ["train", "fit", "bench", "evaluate", "report"])
def test_a_stop_is_one_line_on_stderr(entry: str, tmp_path: Path) -> None:
    args, kind = _cases(tmp_path)[entry]
    done = subprocess.run(
        [sys.executable, "-m", *args], cwd=tmp_path, capture_output=True, text=True,
        timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    lines = [line for line in done.stderr.splitlines() if line.startswith(f"{kind}: ")]
    assert done.returncode == 2 and len(lines) == 1, done.stdout + done.stderr
    assert kind not in done.stdout and "ERROR" not in done.stdout, done.stdout
    assert "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "fit").exists()  # the refused fit left no folder
