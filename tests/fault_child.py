"""The child process of the fault-injection tests: `python -m mbrl_delan.train` run in a
process forked from a server that has imported it (`start`), which SIGKILLs itself at a chosen
moment of the run, or there has a write fail with an OS error (a full disk, a lost permission).

A moment is (phase, n): the n-th event of that phase in the process, counted from its start.

- ``fit``: an optimiser epoch of a model fit (`optimizer_epoch`).
- ``collect``, ``evaluate``: an env step of a training episode, of an evaluation episode (the
  oracle's included).
- ``checkpoint``: the n-th checkpoint is cut: half of its bytes reach the temporary file.
- ``checkpoint_prev``: between keeping ``checkpoint.pt.prev`` and renaming the new one.
- ``metrics``: the n-th line of ``metrics.jsonl`` is torn: half of it reaches the file.

Each process writes how many events of each phase it saw to ``<log>.counts.json`` on a normal
exit, so a test can draw moments that a run reaches.
"""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import signal
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mbrl_delan.train
from mbrl_delan.envs.real import MujocoTaskEnv
from mbrl_delan.training import checkpoint, fit, loop, recorder

# imported once by the fork server (this module itself is not on the server's path)
PRELOAD = ["mbrl_delan.train"]
PHASES = ("fit", "collect", "evaluate", "checkpoint", "checkpoint_prev", "metrics")


class _Torn:
    """A text file whose next write writes half its text, then `fail`s."""

    def __init__(self, file: Any, fail: Callable[[], None]) -> None:
        self.file, self.fail = file, fail

    def write(self, text: str) -> None:
        self.file.write(text[: len(text) // 2])
        self.file.flush()
        self.fail()

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()


class _Injector:
    """Counts the events of each phase; at `moment` sends the process `sig` (SIGKILL; SIGINT
    is Ctrl-C), or with `errno` set raises that OSError from the write (checkpoint and
    metrics phases)."""

    def __init__(
        self, moment: tuple[str, int] | None, errno: int | None, sig: int = signal.SIGKILL
    ) -> None:
        self.moment, self.errno, self.counts, self.phase = moment, errno, Counter(), ""
        self.sig = sig

    def event(self, phase: str) -> bool:
        """Count one event; True when it is the moment of the fault."""
        self.counts[phase] += 1
        return self.moment == (phase, self.counts[phase])

    def fail(self) -> None:
        if self.errno is None:
            os.kill(os.getpid(), self.sig)
            return
        raise OSError(self.errno, os.strerror(self.errno))

    def install(self) -> None:
        """Wrap the functions whose calls are the events."""
        self._wrap(fit, "optimizer_epoch", lambda: self.event("fit") and self.fail())
        for method, phase in (("_collect", "collect"), ("evaluate", "evaluate")):
            self._phase(loop.MBRLLoop, method, phase)
        self._wrap(
            MujocoTaskEnv, "step", lambda: self.phase and self.event(self.phase) and self.fail()
        )
        self._cut_checkpoints()
        self._tear_metrics()

    @staticmethod
    def _wrap(owner: Any, name: str, before: Callable[[], object]) -> None:
        original = getattr(owner, name)

        def wrapped(*args: Any, **kwargs: Any) -> Any:
            before()
            return original(*args, **kwargs)

        setattr(owner, name, wrapped)

    def _phase(self, owner: type, name: str, phase: str) -> None:
        original = getattr(owner, name)

        def wrapped(*args: Any, **kwargs: Any) -> Any:
            self.phase = phase
            try:
                return original(*args, **kwargs)
            finally:
                self.phase = ""

        setattr(owner, name, wrapped)

    def _cut_checkpoints(self) -> None:
        atomic_write, keep_previous = checkpoint.atomic_write, checkpoint._keep_previous

        def cut_write(path: Any, write: Callable[[Any], None], keep_prev: bool) -> None:
            if not self.event("checkpoint"):
                return atomic_write(path, write, keep_prev)

            def half(f: Any) -> None:
                buffer = io.BytesIO()
                write(buffer)
                f.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
                f.flush()
                os.fsync(f.fileno())
                self.fail()

            return atomic_write(path, half, keep_prev)

        def kept_then_die(path: Any) -> None:
            keep_previous(path)
            if self.event("checkpoint_prev"):
                self.fail()

        checkpoint.atomic_write, checkpoint._keep_previous = cut_write, kept_then_die

    def _tear_metrics(self) -> None:
        log = recorder.Recorder.log

        def torn(rec: recorder.Recorder, metrics: Any, iteration: int) -> None:
            if self.event("metrics"):
                rec._file = _Torn(rec._file, self.fail)
            log(rec, metrics, iteration)

        recorder.Recorder.log = torn


def _child(
    argv: list[str], moment: tuple[str, int] | None, errno: int | None, log_file: str, sig: int
) -> None:
    """The forked process: output to `log_file`, the injector installed, the command run."""
    fd = os.open(log_file, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.environ.update(WANDB_MODE="disabled", HYDRA_MAIN_MODULE="__main__")
    signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C as in a shell
    injector = _Injector(moment, errno, sig)
    injector.install()
    sys.argv = ["train", *argv]
    code = 0
    try:
        mbrl_delan.train.main()
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else 1
    Path(log_file + ".counts.json").write_text(json.dumps(injector.counts))
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def start(
    argv: list[str],
    moment: tuple[str, int] | None,
    log_file: Path,
    errno: int | None = None,
    sig: int = signal.SIGKILL,
) -> int:
    """Run `python -m mbrl_delan.train *argv` in a forked process that gets signal `sig` at
    `moment` (SIGKILL: it dies; SIGINT: Ctrl-C), or there fails to write with OSError `errno`
    (no moment: runs to its end). -> its exit code (-9 when killed)."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    process = context.Process(target=_child, args=(argv, moment, errno, str(log_file), sig))
    process.start()
    process.join(timeout=300)
    if process.exitcode is None:
        process.kill()
        process.join()
    return process.exitcode
