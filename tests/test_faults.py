"""Fault injection: a tiny training run killed with SIGKILL at random moments (fits, collection,
evaluation, checkpoint and metrics writes) and resumed ends with the uninterrupted run's result,
record for record and weight for weight; a write failing with a full disk or a lost permission
is exit 2 naming the file, and the resume ends the same way; cut checkpoints and torn records
are recovered; then the writers and the checkpoint reader on their own.

The runs are processes forked from a server that has imported the entry point
(`fault_child.start`), so each costs its run's time, not torch's import."""

from __future__ import annotations

import errno
import json
import logging
import os
import random
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fault_child import PHASES, start
from tiny import TINY_TRAIN

from mbrl_delan.training import Recorder, read_metrics
from mbrl_delan.training.checkpoint import (
    CheckpointError,
    RunWriteError,
    load_checkpoint,
    prev_path,
    save_checkpoint,
)
from mbrl_delan.training.run_lock import RunLock, RunLockedError
from mbrl_delan.training.summary import TIMING_KEYS

RUN = [*TINY_TRAIN, "env.episode_len=10", "budget.iterations=2"]
KILLS = 10
SEED = 0  # of the moments drawn


def _records(run_dir: Path) -> list[dict]:
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING_KEYS} for line in lines]


# what differs between two processes of the same run: the times, the command (a resume's) and
# the host's load when it started
PER_PROCESS = (*TIMING_KEYS, "command", "host")


def _summary(run_dir: Path) -> dict:
    summary = json.loads((run_dir / "summary.json").read_text())
    return {k: v for k, v in summary.items() if k not in PER_PROCESS}


def _weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(run_dir / "checkpoint.pt", weights_only=False)["loop"]["model"]


def _moments(counts: dict[str, int]) -> list[tuple[str, int]]:
    """Ten moments a run reaches: every phase at least once, the rest of any phase."""
    rng = random.Random(SEED)
    phases = [*PHASES, *rng.choices(PHASES, k=KILLS - len(PHASES))]
    return [(phase, rng.randint(1, counts[phase])) for phase in phases]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, int]]:
    """The uninterrupted run and how many events of each phase it had."""
    run_dir = tmp_path_factory.mktemp("faults") / "reference"
    log = run_dir.parent / "reference.log"
    assert start([*RUN, f"hydra.run.dir={run_dir}"], None, log) == 0, log.read_text()
    counts = json.loads(Path(f"{log}.counts.json").read_text())
    assert set(counts) == set(PHASES), counts
    return run_dir, counts


@pytest.mark.heavy
def test_runs_killed_at_ten_random_moments_resume_to_the_uninterrupted_result(
    reference: tuple[Path, dict[str, int]], tmp_path: Path
) -> None:
    ref_dir, counts = reference
    reference_weights = _weights(ref_dir)
    for i, (phase, n) in enumerate(_moments(counts)):
        run_dir, log = tmp_path / f"{i}_{phase}_{n}", tmp_path / f"{i}_{phase}_{n}.log"
        memmap = f"buffer.memmap={i % 2 == 0}"  # either storage gives the reference's result
        code = start([*RUN, memmap, f"hydra.run.dir={run_dir}"], (phase, n), log)
        assert code == -9, f"{phase} {n}: exit {code}\n{log.read_text()}"
        code = start([f"resume={run_dir}"], None, log)
        assert code == 0, f"{phase} {n}: the resume exited {code}\n{log.read_text()}"
        assert _records(run_dir) == _records(ref_dir), (phase, n)
        assert _summary(run_dir) == _summary(ref_dir), (phase, n)
        weights = _weights(run_dir)
        for name, value in reference_weights.items():
            assert torch.equal(weights[name], value), (phase, n, name)
        leftovers = [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]
        assert not leftovers, (phase, n, leftovers)


@pytest.mark.parametrize("budget", ["budget.iterations=2", "budget.env_steps=30"])
def test_a_run_killed_in_its_last_evaluation_episode_resumes_with_that_episode_alone(
    tmp_path: Path, budget: str
) -> None:
    """Killed in the third of three final evaluation episodes (10 env steps each): the resume
    collects nothing, steps only that episode again, and ends with the uninterrupted run's
    records and summary; also when the run ends at an env-step budget, which the last round's
    collected steps already reach while its evaluation is under way."""
    run = [*RUN, "budget.iterations=5", budget, "budget.final_eval_episodes=3"]
    ref_dir, ref_log = tmp_path / "reference", tmp_path / "reference.log"
    assert start([*run, f"hydra.run.dir={ref_dir}"], None, ref_log) == 0, ref_log.read_text()
    evaluated = json.loads(Path(f"{ref_log}.counts.json").read_text())["evaluate"]
    run_dir, log = tmp_path / "run", tmp_path / "run.log"
    code = start([*run, f"hydra.run.dir={run_dir}"], ("evaluate", evaluated - 3), log)
    assert code == -9, log.read_text()
    resumed = tmp_path / "resume.log"
    assert start([f"resume={run_dir}"], None, resumed) == 0, resumed.read_text()
    counts = json.loads(Path(f"{resumed}.counts.json").read_text())
    assert counts.get("collect", 0) == 0 and counts["evaluate"] == 10, counts
    assert _records(run_dir) == _records(ref_dir)
    assert _summary(run_dir) == _summary(ref_dir)


def test_a_run_killed_in_its_third_oracle_episode_resumes_with_that_episode(
    tmp_path: Path,
) -> None:
    """Killed in the third of three (unpaired) oracle episodes: the resume plans the first two
    no more (20 env steps fewer than the whole run) and ends with the uninterrupted run's
    records and summary (the oracle's planner stream goes on from the checkpoint)."""
    run = [*RUN, "budget.oracle_episodes=3"]
    ref_dir, ref_log = tmp_path / "reference", tmp_path / "reference.log"
    assert start([*run, f"hydra.run.dir={ref_dir}"], None, ref_log) == 0, ref_log.read_text()
    evaluated = json.loads(Path(f"{ref_log}.counts.json").read_text())["evaluate"]
    run_dir, log = tmp_path / "run", tmp_path / "run.log"
    assert start([*run, f"hydra.run.dir={run_dir}"], ("evaluate", 25), log) == -9
    resumed = tmp_path / "resume.log"
    assert start([f"resume={run_dir}"], None, resumed) == 0, resumed.read_text()
    counts = json.loads(Path(f"{resumed}.counts.json").read_text())
    assert counts["evaluate"] == evaluated - 20, counts
    assert _records(run_dir) == _records(ref_dir)
    assert _summary(run_dir) == _summary(ref_dir)


@pytest.mark.slow
def test_a_tree_run_killed_in_its_first_round_resumes_into_planning_then_fits(
    tmp_path: Path,
) -> None:
    """model=tree killed while collecting its first on-policy episode: the resume plans before
    it fits again (the tree's constants first built under inference mode) and finishes."""
    run = [*RUN, "env=humanoid_stand", "model=tree", "budget.iterations=1"]
    run_dir, log = tmp_path / "tree", tmp_path / "tree.log"
    assert start([*run, f"hydra.run.dir={run_dir}"], ("collect", 13), log) == -9, log.read_text()
    resumed = tmp_path / "resume.log"
    assert start([f"resume={run_dir}"], None, resumed) == 0, resumed.read_text()
    assert (run_dir / "summary.json").is_file()


def _copy(ref_dir: Path, tmp_path: Path) -> Path:
    run_dir = tmp_path / "run"
    shutil.copytree(ref_dir, run_dir)
    return run_dir


def _resume(run_dir: Path, *overrides: str) -> tuple[int, str]:
    log = run_dir.parent / "resume.log"
    code = start([f"resume={run_dir}", *overrides], None, log)
    return code, log.read_text()


@pytest.mark.parametrize("kept", [0.1, 0.5, 0.9])
def test_a_cut_checkpoint_resumes_from_the_previous_one_to_the_same_result(
    reference: tuple[Path, dict[str, int]], tmp_path: Path, kept: float
) -> None:
    """The finished run's checkpoint cut to `kept` of its size: the resume warns naming both
    files, runs the last round again from ``checkpoint.pt.prev`` and ends where the run did."""
    ref_dir, _ = reference
    run_dir = _copy(ref_dir, tmp_path)
    ckpt = run_dir / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[: int(ckpt.stat().st_size * kept)])
    code, text = _resume(run_dir)
    assert code == 0, text
    assert f"checkpoint {ckpt} is unreadable" in text and f"{ckpt}.prev" in text, text
    assert _records(run_dir) == _records(ref_dir)
    assert _summary(run_dir) == _summary(ref_dir)


def _files(run_dir: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}


def test_ctrl_c_is_one_line_naming_the_resume_and_the_resume_ends_as_the_run(
    reference: tuple[Path, dict[str, int]], tmp_path: Path
) -> None:
    """SIGINT (Ctrl-C) in the middle of collecting: exit 130, no traceback, one line naming
    the run dir and the resume command; that command ends where the uninterrupted run did."""
    ref_dir, counts = reference
    run_dir, log = tmp_path / "run", tmp_path / "run.log"
    moment = ("collect", (counts["collect"] + 1) // 2)
    code = start([*RUN, f"hydra.run.dir={run_dir}"], moment, log, sig=signal.SIGINT)
    text = log.read_text()
    assert code == 130 and "Traceback" not in text and "ERROR" not in text, text
    stops = [line for line in text.splitlines() if "Ctrl-C" in line]
    assert len(stops) == 1, text
    assert f"python -m mbrl_delan.train resume={run_dir}" in stops[0], text
    code, text = _resume(run_dir)
    assert code == 0, text
    assert _records(run_dir) == _records(ref_dir)
    assert _summary(run_dir) == _summary(ref_dir)


@pytest.mark.parametrize(
    ("override", "named"),
    [("device=cuda", "device"), ("budget.iterations=-1", "budget.iterations"),
     ("model.hidden=7", "model.hidden")],
)  # fmt: skip
def test_a_refused_resume_leaves_every_file_as_it_was(
    reference: tuple[Path, dict[str, int]], tmp_path: Path, override: str, named: str
) -> None:
    """A resume whose overrides are refused (a device the host lacks, a bad budget, a key a
    resume cannot change) is exit 2 in one line naming the key, and the run's folder keeps
    every byte: no config change, no log, no crash marker."""
    if override == "device=cuda" and torch.cuda.is_available():
        pytest.skip("the host has CUDA: device=cuda is not refused")
    run_dir = _copy(reference[0], tmp_path)
    before = _files(run_dir)
    code, text = _resume(run_dir, override)
    assert code == 2 and "Traceback" not in text and named in text, text
    assert len(text.strip().splitlines()) <= 3, text
    assert _files(run_dir) == before
    code, text = _resume(run_dir)  # the plain resume of the finished run still works
    assert code == 0, text


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_resume_of_a_read_only_run_dir_is_one_line(
    reference: tuple[Path, dict[str, int]], tmp_path: Path
) -> None:
    run_dir = _copy(reference[0], tmp_path)
    before = _files(run_dir)
    run_dir.chmod(0o555)
    try:
        code, text = _resume(run_dir)
    finally:
        run_dir.chmod(0o755)
    assert code == 2 and "Traceback" not in text and str(run_dir) in text, text
    assert len(text.strip().splitlines()) <= 3, text
    assert _files(run_dir) == before


def test_a_mistyped_resume_creates_nothing(tmp_path: Path) -> None:
    missing = tmp_path / "runs" / "typo"
    code = start([f"resume={missing}"], None, tmp_path / "resume.log")
    text = (tmp_path / "resume.log").read_text()
    assert code == 2 and "Traceback" not in text and f"resume='{missing}'" in text, text
    assert not (tmp_path / "runs").exists()


def test_two_cuts_in_a_row_recover(reference: tuple[Path, dict[str, int]], tmp_path: Path) -> None:
    """Cut, resume, cut, resume: the first fallback sets the damaged file aside (named in its
    warning) and keeps the good one as the backup, so the second cut recovers too."""
    ref_dir, _ = reference
    run_dir = _copy(ref_dir, tmp_path)
    ckpt = run_dir / "checkpoint.pt"
    for cut in (1, 2):
        ckpt.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
        code, text = _resume(run_dir)
        assert code == 0, f"cut {cut}: {text}"
        assert f"the damaged file is kept as {ckpt}.damaged" in text, text
        assert _records(run_dir) == _records(ref_dir), cut
        assert _summary(run_dir) == _summary(ref_dir), cut
        assert load_checkpoint(ckpt, weights_only=False)  # a fresh, readable checkpoint


def test_a_resume_killed_after_a_fallback_loads_the_backup(tmp_path: Path) -> None:
    """The damaged checkpoint set aside and nothing saved since: the backup is loaded."""
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"round": torch.tensor(1)})
    save_checkpoint(path, {"round": torch.tensor(2)})
    path.write_bytes(b"cut")
    assert int(load_checkpoint(path, set_aside=True)["round"]) == 1
    assert not path.exists() and (tmp_path / "checkpoint.pt.damaged").read_bytes() == b"cut"
    assert int(load_checkpoint(path)["round"]) == 1
    save_checkpoint(path, {"round": torch.tensor(2)})
    assert int(load_checkpoint(prev_path(path))["round"]) == 1  # the good one stays the backup


def test_a_second_writer_exits_2_naming_the_first(
    reference: tuple[Path, dict[str, int]], tmp_path: Path
) -> None:
    """While another process holds the run dir's lock (a live run; here the test itself), a
    resume of it is exit 2 in one line naming that pid, and every file stays as it was; once
    the lock is free the resume ends as the run did."""
    run_dir = _copy(reference[0], tmp_path)
    holder = RunLock(run_dir)
    holder.acquire()
    try:
        before = _files(run_dir)
        code, text = _resume(run_dir)
        assert code == 2 and "Traceback" not in text, text
        assert f"is in use by another process (pid {os.getpid()})" in text, text
        assert len(text.strip().splitlines()) <= 3, text
        assert _files(run_dir) == before
    finally:
        holder.release()
    code, text = _resume(run_dir)
    assert code == 0, text
    assert _records(run_dir) == _records(reference[0])


def test_a_run_lock_is_one_holder_at_a_time_and_freed_by_its_end(tmp_path: Path) -> None:
    """Two locks of one folder: the second names the first's pid; after a release, or the
    holder's death (SIGKILL), the folder is free."""
    first = RunLock(tmp_path)
    first.acquire()
    with pytest.raises(RunLockedError, match=f"pid {os.getpid()}"):
        RunLock(tmp_path).acquire()
    first.release()
    child = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; "
         "from mbrl_delan.training.run_lock import RunLock; lock = RunLock(Path(sys.argv[1])); "
         "lock.acquire(); print('held', flush=True); time.sleep(600)", str(tmp_path)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert child.stdout.readline().strip() == "held"
        with pytest.raises(RunLockedError, match=f"pid {child.pid}"):
            RunLock(tmp_path).acquire()
    finally:
        child.kill()
        child.wait()
    second = RunLock(tmp_path)
    second.acquire()
    second.release()


def test_both_checkpoints_cut_is_exit_2_naming_them_and_deleting_nothing(
    reference: tuple[Path, dict[str, int]], tmp_path: Path
) -> None:
    """Both checkpoints cut: one line naming each file and its error, every file kept."""
    run_dir = _copy(reference[0], tmp_path)
    for name in ("checkpoint.pt", "checkpoint.pt.prev"):
        path = run_dir / name
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    code, text = _resume(run_dir)
    assert code == 2 and "Traceback" not in text, text
    assert f"cannot read checkpoint {run_dir / 'checkpoint.pt'}" in text, text
    assert f"nor its previous version {run_dir / 'checkpoint.pt.prev'}" in text, text
    after = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    assert after.pop("train.log").startswith(before.pop("train.log"))  # the attempt's lines
    after.pop(".lock"), before.pop(".lock")  # the lock file: the last writer's pid
    assert "crash.json" in after  # the failed resume, for `report` and sweeps
    assert {name: after[name] for name in before} == before


@pytest.mark.parametrize("kept", [0.0, 0.3, 0.9])
def test_a_torn_last_record_is_restored_from_the_checkpoint(
    reference: tuple[Path, dict[str, int]], tmp_path: Path, kept: float
) -> None:
    """The finished run's last line of metrics.jsonl cut to `kept` of its length (0: lost):
    the resume restores it from the checkpoint's copy, exits 0 and leaves the summary alone."""
    ref_dir, _ = reference
    run_dir = _copy(ref_dir, tmp_path)
    metrics = run_dir / "metrics.jsonl"
    *head, last = metrics.read_text().splitlines(keepends=True)
    metrics.write_text("".join(head) + last[: int(len(last) * kept)])
    summary = (run_dir / "summary.json").read_bytes()
    code, text = _resume(run_dir)
    assert code == 0 and "restored from the checkpoint" in text, text
    assert metrics.read_text() == (ref_dir / "metrics.jsonl").read_text()
    assert (run_dir / "summary.json").read_bytes() == summary


def test_a_torn_record_of_an_unfinished_run_is_restored_and_the_run_goes_on(
    reference: tuple[Path, dict[str, int]], tmp_path: Path
) -> None:
    """A run of one round with its record torn, resumed with a second round: the first
    round's record comes back from the checkpoint and the run ends as the two-round one."""
    ref_dir, _ = reference
    run_dir, log = tmp_path / "one_round", tmp_path / "one_round.log"
    one_round = [*RUN, "budget.iterations=1", f"hydra.run.dir={run_dir}"]
    assert start(one_round, None, log) == 0, log.read_text()
    metrics = run_dir / "metrics.jsonl"
    metrics.write_text(metrics.read_text()[:40])
    code, text = _resume(run_dir, "budget.iterations=2")
    assert code == 0 and "restored from the checkpoint" in text, text
    assert _records(run_dir) == _records(ref_dir)
    assert _summary(run_dir) == _summary(ref_dir)


@pytest.mark.parametrize("phase", ["checkpoint", "metrics"])
@pytest.mark.parametrize("errno_", [errno.ENOSPC, errno.EACCES])
def test_a_write_that_fails_is_exit_2_naming_it_and_the_resume_ends_as_the_run(
    reference: tuple[Path, dict[str, int]], tmp_path: Path, phase: str, errno_: int
) -> None:
    """Half of a checkpoint or a metrics record written, then the OS error: exit 2 with one
    line naming the file and the error; the resume (the cause gone) ends where the run did."""
    ref_dir, counts = reference
    run_dir, log = tmp_path / "run", tmp_path / "run.log"
    moment = (phase, (counts[phase] + 1) // 2)
    code = start([*RUN, f"hydra.run.dir={run_dir}"], moment, log, errno_)
    text = log.read_text()
    assert code == 2 and "Traceback" not in text, text
    path = run_dir / ("checkpoint.pt" if phase == "checkpoint" else "metrics.jsonl")
    errors = [line for line in text.splitlines() if line.startswith("write error: ")]
    assert len(errors) == 1, text
    assert f"cannot write {path}: {os.strerror(errno_)} (errno {errno_})" in errors[0], text
    assert "Error executing job" not in text, text  # Hydra's own line: the task caught it
    if phase == "checkpoint":  # the run has a checkpoint to continue from
        assert f"python -m mbrl_delan.train resume={run_dir}" in errors[0], text
    code, text = _resume(run_dir)
    assert code == 0, text
    assert _records(run_dir) == _records(ref_dir)
    assert _summary(run_dir) == _summary(ref_dir)


# --- the writers and the reader, faults raised in-process -----------------------------------


def test_crash_before_replace_leaves_previous_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"iteration": 1})
    save_checkpoint(path, {"iteration": 2})

    def crash(src, dst):
        raise OSError("simulated crash before the rename")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(RunWriteError, match="ckpt.pt: simulated crash before the rename"):
        save_checkpoint(path, {"iteration": 3})
    monkeypatch.undo()
    assert load_checkpoint(path)["iteration"] == 2
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # temp cleaned up


def test_crash_at_final_replace_keeps_main_and_prev(tmp_path, monkeypatch):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"iteration": 1})
    real_replace = os.replace

    def crash_on_main(src, dst):
        if os.fspath(dst) == os.fspath(path):
            raise OSError("simulated crash")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crash_on_main)
    kept = "simulated crash; .* MB free on the disk mounted at .*; kept as they were: ckpt.pt"
    with pytest.raises(RunWriteError, match=kept):
        save_checkpoint(path, {"iteration": 2})
    monkeypatch.undo()
    assert load_checkpoint(path)["iteration"] == 1
    assert load_checkpoint(prev_path(path))["iteration"] == 1


def test_corrupt_checkpoint_falls_back_to_prev(tmp_path, caplog):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"iteration": 1})
    save_checkpoint(path, {"iteration": 2})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # a torn write
    with caplog.at_level(logging.WARNING):
        state = load_checkpoint(path)
    assert state["iteration"] == 1
    assert "unreadable" in caplog.text and "ckpt.pt" in caplog.text


@pytest.mark.parametrize("kept", [0.01, 0.1, 0.25, 0.5, 0.99])
def test_a_checkpoint_cut_anywhere_falls_back_to_prev(tmp_path, kept):
    """A cut zip archive fails in several ways (OSError EINVAL near its start, a missing
    central directory later): each falls back to the intact previous checkpoint."""
    path = tmp_path / "ckpt.pt"
    weights = torch.arange(200_000, dtype=torch.float32)
    save_checkpoint(path, {"iteration": 1, "w": weights})
    save_checkpoint(path, {"iteration": 2, "w": weights})
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * kept)])
    state = load_checkpoint(path)
    assert state["iteration"] == 1 and torch.equal(state["w"], weights)


def test_missing_and_unreadable_checkpoints_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        load_checkpoint(tmp_path / "nope.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="bad.pt"):
        load_checkpoint(bad)


def test_a_full_disk_inside_torch_save_names_the_file_and_keeps_the_checkpoints(
    tmp_path, monkeypatch
):
    """torch.save reports ENOSPC as RuntimeError "unexpected pos": a RunWriteError names the
    file; checkpoint.pt and its .prev are as they were; no temp file is left."""
    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"step": 1})
    save_checkpoint(path, {"step": 2})
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def full(obj, f, *args, **kwargs):
        f.write(b"PK\x03\x04partial")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(RunWriteError, match=r"cannot write .*checkpoint.pt: .*unexpected pos"):
        save_checkpoint(path, {"step": 3})
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 2


@pytest.mark.parametrize("errno_", [errno.ENOSPC, errno.EACCES])
def test_metrics_that_cannot_be_written_name_the_file_and_keep_the_records(tmp_path, errno_):
    rec = _recorder(tmp_path)
    rec.log({"env_steps": 15}, iteration=1)

    class Failing:
        def write(self, text):
            raise OSError(errno_, os.strerror(errno_))

        def flush(self):
            pass

        def close(self):
            pass

    rec._file = Failing()
    with pytest.raises(RunWriteError, match=f"metrics.jsonl: {os.strerror(errno_)}"):
        rec.log({"env_steps": 30}, iteration=2)
    assert read_metrics(tmp_path / "metrics.jsonl") == [{"iteration": 1, "env_steps": 15}]


def _recorder(run_dir: Path) -> Recorder:
    return Recorder(run_dir, "none", "test", None, {"seed": 0})


@pytest.mark.parametrize("errno_", [errno.ENOSPC, errno.EACCES])
@pytest.mark.parametrize("writer", ["checkpoint", "summary"])
def test_an_os_error_in_a_writer_names_the_file_and_keeps_its_last_version(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, writer: str, errno_: int
) -> None:
    """The OS error from the file's write: a RunWriteError naming the file, the error and the
    free space; the file's last version as it was, no temporary file left."""
    rec = _recorder(tmp_path)
    path = tmp_path / ("checkpoint.pt" if writer == "checkpoint" else "summary.json")

    def write(step: int) -> None:
        if writer == "checkpoint":
            save_checkpoint(path, {"step": step})
        else:
            rec.write_summary({"step": step})

    write(1)
    write(2)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        raise OSError(errno_, os.strerror(errno_))

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(RunWriteError) as caught:
        write(3)
    monkeypatch.setattr(os, "fsync", real_fsync)
    message = str(caught.value)
    assert message.startswith(f"cannot write {path}: {os.strerror(errno_)} (errno {errno_})")
    assert "MB free on the disk mounted at " in message
    assert f"kept as they were: {path.name}" in message
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_full_disk_at_the_start_names_the_folder_and_leaves_none(tmp_path, monkeypatch):
    """`check_writable` (before Hydra writes its record) writes real bytes: a full disk fails
    there, naming the path and the reason, and the folder it made is gone."""
    from mbrl_delan.training import checkpoint

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoint.os, "fsync", full)
    folder = tmp_path / "runs" / "new"
    with pytest.raises(RunWriteError, match=f"{folder}.*No space left on device"):
        checkpoint.check_writable(folder)
    assert not folder.exists()


@pytest.mark.parametrize("program", ["-m", "/venv/bin/mbrl-delan-train"])
def test_ctrl_c_while_an_entry_point_imports_is_one_line(program: str) -> None:
    """Ctrl-C during an entry point's imports (`python -m mbrl_delan.X` or a console script,
    before its own handling begins): one line on stderr, no traceback, the process ends as
    by SIGINT; a user's program that imports the package keeps Python's own traceback."""
    entry = f"import sys; sys.argv[0] = {program!r}; import mbrl_delan; raise KeyboardInterrupt"
    out = subprocess.run([sys.executable, "-c", entry], capture_output=True, text=True,
                         timeout=60)  # fmt: skip
    assert out.returncode in (-signal.SIGINT, 130), out
    assert out.stderr == "stopped (Ctrl-C) while starting: nothing was written\n", out.stderr
    user = "import mbrl_delan; raise KeyboardInterrupt"
    out = subprocess.run([sys.executable, "-c", user], capture_output=True, text=True, timeout=60)
    assert "Traceback" in out.stderr and "KeyboardInterrupt" in out.stderr, out.stderr
