"""Hydra sweeps: launchers (submitit local and SLURM, joblib), crash markers, wandb groups."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from tiny import TINY_TRAIN

from mbrl_delan.conf.checks import CONFIG_DIR
from mbrl_delan.report import main as report_main
from mbrl_delan.sweep import CRASH_FILE, marks_crash, sweep_name

CONFIGS = CONFIG_DIR

TINY = [*TINY_TRAIN, "budget.iterations=1"]


def sweep(sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "mbrl_delan.train",
        "-m",
        *TINY,
        f"hydra.sweep.dir={sweep_dir}",
        *overrides,
    ]
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONUNBUFFERED": "1"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)


def report_rows(sweep_dir: Path) -> list[dict[str, str]]:
    assert report_main([str(sweep_dir)]) == 0
    assert (sweep_dir / "report.md").is_file()
    with (sweep_dir / "report.csv").open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
@pytest.mark.heavy
def test_submitit_local_sweep_runs_each_job_in_its_own_folder(tmp_path: Path) -> None:
    sweep_dir = tmp_path / "multirun" / "sweep"
    out = sweep(sweep_dir, "seed=0,1", "hydra/launcher=submitit_local")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    runs = sorted(p.parent for p in sweep_dir.glob("*/summary.json"))
    assert [r.name for r in runs] == ["0_pendulum_delan_mppi_s0", "1_pendulum_delan_mppi_s1"]
    for seed, run in enumerate(runs):
        assert json.loads((run / "summary.json").read_text())["seed"] == seed
        # the wandb group of a multirun defaults to the sweep's name
        assert OmegaConf.load(run / "config.yaml").logger.group == "multirun_sweep"
    assert (sweep_dir / ".submitit").is_dir()  # submitit's job logs and pickles
    (row,) = report_rows(sweep_dir)
    assert row["seeds"] == "0 1" and row["n"] == "2"
    assert "None." in (sweep_dir / "report.md").read_text()  # no incomplete runs


@pytest.mark.slow
@pytest.mark.heavy
def test_joblib_sweep_runs_its_jobs_in_parallel_processes(tmp_path: Path) -> None:
    sweep_dir = tmp_path / "sweep"
    out = sweep(
        sweep_dir, "planner.horizon=4,5", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    horizons = sorted(
        OmegaConf.load(run / "config.yaml").planner.horizon
        for run in sweep_dir.glob("*_pendulum_delan_mppi_s0")
        if (run / "summary.json").is_file()
    )
    assert horizons == [4, 5]


def test_a_sweep_with_bad_members_runs_none_and_names_each_in_one_line(tmp_path: Path) -> None:
    """Two of four members with a bad value: exit 2 before any job runs, one line per bad
    member (its number, swept values and the error), no sweep folder."""
    sweep_dir = tmp_path / "sweep"
    out = sweep(sweep_dir, "planner.horizon=0,5", "budget.eval_every=1,-1")
    text = out.stdout + out.stderr
    assert out.returncode == 2 and "Traceback" not in text, text
    lines = [line for line in text.splitlines() if "config error" in line]
    # Hydra orders the members by the keys' first place on the command line: TINY's eval_every
    assert len(lines) == 3, text  # members 0 and 2 (horizon 0), 3 (eval_every -1); 1 is good
    assert "#0 (budget.eval_every=1 planner.horizon=0): planner.horizon=0 is not" in lines[0]
    assert "#3 (budget.eval_every=-1 planner.horizon=5): budget.eval_every=-1" in lines[2]
    assert not sweep_dir.exists()


FAKE_SBATCH = """#!/bin/sh
cp "$1" "$FAKE_SLURM_DIR/submitted.sh"
echo "Submitted batch job 4242"
"""


def test_slurm_launcher_config_renders_an_sbatch_script(tmp_path: Path, monkeypatch) -> None:
    """`hydra/launcher=slurm` through the submitit plugin to sbatch, with a fake sbatch."""
    import submitit
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    import mbrl_delan.train  # noqa: F401 - registers the config's resolvers

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, text in (("sbatch", FAKE_SBATCH), ("srun", "#!/bin/sh\n")):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_SLURM_DIR", str(tmp_path))
    monkeypatch.setattr(submitit.SlurmJob, "results", lambda self: [None])  # no cluster to wait on
    overrides = [
        "hydra/launcher=slurm",
        "hydra.launcher.partition=debug",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        "hydra.job.name=train",
    ]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("config", overrides=overrides, return_hydra_config=True)
    launcher = instantiate(cfg.hydra.launcher)
    launcher.config = cfg
    assert launcher.launch([["seed=0"], ["seed=1"]], initial_job_idx=0) == [None, None]
    script = (tmp_path / "submitted.sh").read_text()
    for line in (
        "--array=0-1%2",  # both jobs of the sweep at once (array_parallelism: 64)
        "--partition=debug",
        "--time=120",
        "--cpus-per-task=1",
        "--mem=4GB",
        "--job-name=train",
    ):
        assert f"#SBATCH {line}\n" in script
    assert f"{tmp_path / 'sweep'}/.submitit/" in script


def test_crash_json_is_written_and_the_exception_propagates(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")
    lines = [json.dumps({"iteration": k, "env_steps": 10 * k}) for k in (1, 2)]
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    cfg = OmegaConf.create({"resume": str(run), "fail": True})

    @marks_crash
    def fake_train(cfg) -> str:
        if cfg.fail:
            raise ValueError("the model diverged")
        return "done"

    with pytest.raises(ValueError, match="the model diverged"):
        fake_train(cfg)
    crash = json.loads((run / CRASH_FILE).read_text())
    assert crash["type"] == "ValueError" and crash["message"] == "the model diverged"
    assert crash["iteration"] == 2  # the last iteration in metrics.jsonl
    assert "Traceback" in crash["traceback"] and crash["time"].endswith("+00:00")
    cfg.fail = False
    assert fake_train(cfg) == "done"
    assert not (run / CRASH_FILE).exists()  # a successful resume clears the marker


def test_no_crash_json_without_a_run_dir(tmp_path: Path) -> None:
    @marks_crash
    def fake_train(cfg) -> None:
        raise KeyError("x")

    with pytest.raises(KeyError):
        fake_train(OmegaConf.create({"resume": str(tmp_path)}))  # not a run dir: no config.yaml
    assert not (tmp_path / CRASH_FILE).exists()


def test_sweep_name() -> None:
    assert sweep_name("runs/multirun/2026-11-21/18-24-22") == "2026-11-21_18-24-22"
    assert sweep_name("grid") == "grid"
