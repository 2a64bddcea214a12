"""Bookkeeping of runs inside Hydra sweeps: the wandb group of a multirun, and crash markers.

* ``with_sweep_group(cfg)``: in a multirun (``-m``), a run whose ``logger.group`` is null gets
  the sweep's name as its wandb group, so the runs of one sweep are grouped together.
* ``exit_or_raise``: how the entry point ends a failed run without stopping the sweep.
* ``StartChecks``: a Hydra callback that checks the training config, and refuses a folder
  holding another run, before Hydra creates the run dir or writes in it.
* ``marks_crash``: decorates the training entry function; when it raises, the run dir gets
  ``crash.json`` (written atomically) and the exception propagates unchanged. A later
  successful (resumed) run removes the marker.
"""

from __future__ import annotations

import copy
import datetime
import functools
import json
import logging
import shutil
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from mbrl_delan.conf.checks import (
    COMPOSE_ERRORS,
    CONFIG_DIR,
    ConfigError,
    compose_config,
    config_error_line,
    exit_config_error,
    migrate,
    refuse_used_run_dir,
    validate_train_config,
)
from mbrl_delan.stops import stop, stop_line
from mbrl_delan.training.checkpoint import (
    CHECKPOINT_FILE,
    RunWriteError,
    atomic_write,
    check_writable,
)
from mbrl_delan.training.recorder import (
    ITERATION,
    METRICS_FILE,
    RUN_CONFIG,
    SUMMARY_FILE,
    read_metrics,
)
from mbrl_delan.training.run_lock import RunLock, RunLockedError

log = logging.getLogger(__name__)

CRASH_FILE = "crash.json"
TRACEBACK_CHARS = 4000  # the tail of the traceback kept in crash.json
# files that mark a folder as holding a run of mbrl_delan.train (finished, stopped or crashed)
# a run's files: a folder with one of them holds a run (``crash.json`` alone: a start that
# failed before the run's config was written, which a corrected rerun may reuse)
RUN_FILES = (RUN_CONFIG, CHECKPOINT_FILE, METRICS_FILE, SUMMARY_FILE)

T = TypeVar("T")


def sweep_name(sweep_dir: str | Path) -> str:
    """The wandb group of a sweep: its folder's parent and name joined by ``_``.

    ``runs/multirun/2026-11-21/18-24-22`` gives ``2026-11-21_18-24-22`` (no ``/``, which wandb
    names avoid).
    """
    path = Path(sweep_dir)
    return f"{path.parent.name}_{path.name}" if path.parent.name else path.name


def with_sweep_group(cfg: DictConfig) -> DictConfig:
    """``cfg`` with ``logger.group`` set to the sweep's name in a multirun when it is null.

    Single runs, configs outside Hydra and explicit ``logger.group=...`` are left as they are.
    """
    if not HydraConfig.initialized() or cfg.get("logger") is None:
        return cfg
    if not in_multirun() or cfg.logger.get("group") is not None:
        return cfg
    with open_dict(cfg):
        cfg.logger.group = sweep_name(HydraConfig.get().sweep.dir)
    return cfg


def in_multirun() -> bool:
    """Whether this process runs a job of a Hydra multirun (``-m``)."""
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def exit_or_raise(code: int, err: BaseException) -> NoReturn:
    """End a failed run: ``sys.exit(code)`` in a single run; in a multirun re-raise ``err``.

    Hydra's launchers record an exception as that job's failure and run the other jobs (the
    sweep then ends with it), whereas ``SystemExit`` would stop the whole sweep at once.
    """
    if in_multirun():
        raise err
    sys.exit(code)


def crash_dir(cfg: DictConfig) -> Path | None:
    """The run dir a crash of the training of ``cfg`` is recorded in; None when there is none.

    ``resume=<dir>``: that dir if it is a run dir (has ``config.yaml``); otherwise Hydra's output
    dir if it exists (Hydra creates it before the task starts).
    """
    resume = cfg.get("resume")
    if resume:
        run = Path(resume)
        return run if (run / RUN_CONFIG).is_file() else None
    if not HydraConfig.initialized():
        return None
    run = Path(HydraConfig.get().runtime.output_dir)
    return run if run.is_dir() else None


def last_iteration(run_dir: Path, warn: bool = True) -> int | None:
    """The last loop iteration recorded in the run's ``metrics.jsonl``, or None (`warn`:
    name its damaged lines, `read_metrics`)."""
    records = read_metrics(run_dir / METRICS_FILE, warn)
    done = [r[ITERATION] for r in records if ITERATION in r]
    return max(done) if done else None


def write_crash(run_dir: Path, err: BaseException) -> Path:
    """Write ``run_dir/crash.json`` atomically.

    Keys: ``type`` (the exception's class name), ``message`` (``str(err)``), ``iteration``
    (iterations completed before the crash according to ``metrics.jsonl``; null when none),
    ``time`` (UTC, ISO 8601) and ``traceback`` (its last ``TRACEBACK_CHARS`` characters).
    """
    record = {
        "type": type(err).__name__,
        "message": str(err),
        "iteration": last_iteration(run_dir),
        "time": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "traceback": "".join(traceback.format_exception(err))[-TRACEBACK_CHARS:],
    }
    text = json.dumps(record, indent=2) + "\n"
    path = run_dir / CRASH_FILE
    atomic_write(path, lambda f: f.write(text.encode("utf-8")), keep_prev=False)
    return path


def read_crash(run_dir: Path) -> dict[str, Any] | None:
    """The run's ``crash.json`` as a dict; None when absent or unreadable (logged)."""
    path = Path(run_dir) / CRASH_FILE
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        log.warning("unreadable %s: %s", path, err)
        return None
    return record if isinstance(record, dict) else None


def marks_crash(fn: Callable[[DictConfig], T]) -> Callable[[DictConfig], T]:
    """Decorate ``fn(cfg)`` so that an exception it raises leaves ``crash.json`` in the run dir.

    The exception (``KeyboardInterrupt`` included) is re-raised unchanged; a failure to write
    the marker is logged and never hides it. On success a stale ``crash.json`` is removed.
    """

    @functools.wraps(fn)
    def wrapper(cfg: DictConfig) -> T:
        try:
            result = fn(cfg)
        except (Exception, KeyboardInterrupt) as err:
            _record_crash(cfg, err)
            raise
        run = crash_dir(cfg)
        if run is not None:
            (run / CRASH_FILE).unlink(missing_ok=True)
        return result

    return wrapper


def _record_crash(cfg: DictConfig, err: BaseException) -> None:
    try:
        run = crash_dir(cfg)
        if run is not None:
            path = write_crash(run, err)
            if not isinstance(err, KeyboardInterrupt):  # Ctrl-C has its own line
                log.info("run failed (%s: %s); wrote %s", type(err).__name__, err, path)
    except (OSError, ValueError) as write_err:
        log.warning("could not write %s: %s", CRASH_FILE, write_err)


class StartChecks(Callback):
    """Hydra callback of ``python -m mbrl_delan.train`` (``hydra.callbacks`` in
    train's config.yaml): before Hydra creates the run dir or writes its ``.hydra/`` record, the
    composed config is checked (`validate_train_config`) and a new run in a folder that
    holds another run is refused: one line naming the cause, exit code 2, nothing written.
    (Hydra turns a callback's exceptions into warnings, so it exits itself.) A resume is
    checked the same way, its saved config with the command line's overrides (`resumed_config`),
    and so is the folder (a run dir, writable): a refused resume leaves every file as it was.
    Each job of a sweep (``-m``) is checked when it starts: a bad job fails with ``crash.json``
    in its folder while the others run."""

    def __init__(self) -> None:
        self.lock: RunLock | None = None  # the run dir's, from the start to the end of the run

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        cfg = _task_config(config)
        if cfg.get("resume") is not None:
            try:
                run_cfg, _ = resumed_config(config.hydra.overrides.task, cfg)
                validate_train_config(run_cfg)
            except (ConfigError, *COMPOSE_ERRORS) as err:
                exit_config_error(err)
            self.lock = lock_run_dir(Path(cfg.resume))
            return
        run_dir = Path(config.hydra.run.dir)
        instead = f"continue it with resume={run_dir}, or start a new one in another hydra.run.dir"
        try:
            validate_train_config(cfg)
            refuse_used_run_dir(run_dir, RUN_FILES, instead)
        except (ConfigError, *COMPOSE_ERRORS) as err:
            exit_config_error(err)
        self.lock = lock_run_dir(run_dir)

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self.lock is not None:
            self.lock.release()

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """A sweep whose members' configs do not pass the checks runs none of them: one line
        per bad member (its number and overrides, the error), exit 2, before the sweep's
        folder is made. Another sweeper's jobs are checked as each starts."""
        if not str(config.hydra.sweeper.get("_target_", "")).endswith(".BasicSweeper"):
            return  # another sweeper picks its own members
        try:
            members = sweep_members(config)
        except COMPOSE_ERRORS:
            return
        bad = []
        for number, (overrides, label) in enumerate(members):
            try:
                validate_train_config(compose_config(CONFIG_DIR, overrides))
            except (ConfigError, *COMPOSE_ERRORS) as err:
                bad.append((number, label, err))
        for number, label, err in bad:
            stop_line("config error", f"sweep member #{number} ({label}): {config_error_line(err)}")
        if bad:
            sys.exit(2)


def sweep_members(config: DictConfig) -> list[tuple[list[str], str]]:
    """Each job of a basic-sweeper multirun, in Hydra's order: its overrides (the task's
    command line expanded, with the sweeper's `params`; Hydra's search path kept so a
    plugin's config groups are found) and its label (the swept keys' values)."""
    params = config.hydra.sweeper.get("params") or {}
    task = [*(f"{k}={v}" for k, v in params.items()), *config.hydra.overrides.task]
    parsed = OverridesParser.create().parse_overrides(task)
    swept = {o.get_key_element() for o in parsed if o.is_sweep_override()}
    searchpath = [o for o in config.hydra.overrides.hydra if o.startswith("hydra.searchpath")]
    members = [m for batch in BasicSweeper.split_arguments(parsed, None) for m in batch]
    return [
        ([*searchpath, *m], " ".join(o for o in m if o.split("=", 1)[0] in swept)) for m in members
    ]


class WritableRunDir(Callback):
    """Hydra callback of ``python -m mbrl_delan.fit`` and ``python -m mbrl_delan.bench``
    (``hydra.callbacks`` in their config.yaml): a run dir that cannot be made or written ends
    the command with one line naming it and exit 2, before Hydra's log file there fails with a
    raw error. With `lock` (fit) the run dir's `RunLock`
    is held until the run ends: a second writer exits 2 naming the holder."""

    def __init__(self, lock: bool = False) -> None:
        self.take_lock = lock
        self.lock: RunLock | None = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_dir = Path(config.hydra.run.dir)
        if self.take_lock:
            self.lock = lock_run_dir(run_dir)
        else:
            exit_unless_writable(run_dir)

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self.lock is not None:
            self.lock.release()


def discard_unstarted_run_dir(run_dir: Path, log_name: str) -> None:
    """Remove `run_dir` when it holds only what Hydra, the run's lock and a crash marker put
    there before the run wrote anything (``.hydra/``, the log `log_name`, ``.lock``,
    ``crash.json``): a run stopped by its input leaves no folder. A folder with anything else
    in it is left as it is."""
    traces = {".hydra", ".lock", log_name, CRASH_FILE}
    if run_dir.is_dir() and {path.name for path in run_dir.iterdir()} <= traces:
        shutil.rmtree(run_dir, ignore_errors=True)


def lock_run_dir(run_dir: Path) -> RunLock:
    """`exit_unless_writable(run_dir)`, then its `RunLock`, held until the run ends: a folder
    another process writes is one line naming that process and exit 2."""
    exit_unless_writable(run_dir)
    lock = RunLock(run_dir)
    try:
        lock.acquire()
    except RunLockedError as err:
        stop("run in use", err)
    return lock


def exit_unless_writable(run_dir: Path) -> None:
    """`check_writable(run_dir)`; a failure is logged as one line and exits 2."""
    try:
        check_writable(run_dir)
    except RunWriteError as err:
        stop("write error", err)


# command-line keys a resumed run takes over its saved config: how long and where it runs and
# what it logs, not what it is (prefixes: `budget.iterations`, `logger=csv`, `video_width`)
RESUME_OVERRIDABLE = ("budget.", "device", "threads", "logger", "video")


def resume_override_keys(overrides: Sequence[str], cfg: DictConfig, saved: DictConfig) -> list[str]:
    """The keys of a resumed run's command-line `overrides` (Hydra's ``overrides.task``) whose
    value in the composed `cfg` differs from the run's `saved` config. Raises ConfigError
    naming every such key that a resumed run cannot change (any but `RESUME_OVERRIDABLE`),
    before anything is written; an override equal to the saved value is no change."""
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    keys = list(dict.fromkeys(o.key_or_group for o in parsed if o.key_or_group != "resume"))
    changed = [k for k in keys if _plain(cfg, k) != _plain(saved, k)]
    refused = [k for k in changed if not k.startswith(RESUME_OVERRIDABLE)]
    if refused:
        raise ConfigError(
            f"resume={cfg.resume}: a resumed run keeps its config, so {', '.join(refused)} "
            "cannot change (start a new run for that); on resume you may set budget.*, "
            "device, threads, logger and video*"
        )
    return changed


def resumed_config(overrides: Sequence[str], cfg: DictConfig) -> tuple[DictConfig, list[str]]:
    """The config of the run ``cfg.resume`` names: its saved ``config.yaml`` (migrated) with
    the keys of the command line's `overrides` that `resume_override_keys` allows set from the
    composed `cfg`, and those keys. Reads only: the caller writes it once it is checked.
    ConfigError when that folder holds no ``config.yaml``."""
    saved = Path(cfg.resume) / RUN_CONFIG
    if not saved.is_file():
        raise ConfigError(
            f"resume={cfg.resume!r}: no {RUN_CONFIG} in that folder, so it is not "
            "a run dir of mbrl_delan.train"
        )
    run_cfg = migrate(OmegaConf.load(saved))
    keys = resume_override_keys(overrides, cfg, run_cfg)
    for key in keys:
        OmegaConf.update(run_cfg, key, OmegaConf.select(cfg, key), merge=False)
    run_cfg.resume = str(saved.parent)
    return run_cfg, keys


def _plain(cfg: DictConfig, key: str) -> Any:
    """The value at `key` as plain Python (interpolations resolved; None when absent)."""
    value = OmegaConf.select(cfg, key, default=None)
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _task_config(config: DictConfig) -> DictConfig:
    """The task's config: Hydra's full config without its ``hydra`` node."""
    cfg = copy.deepcopy(config)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg
