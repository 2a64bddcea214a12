"""Crash-safe checkpoints and random-number-generator state.

``save_checkpoint`` never leaves a half-written file under the checkpoint's name: the new
content goes to a temporary file in the same folder, is flushed and fsynced, and then takes the
name with ``os.replace`` (atomic on POSIX and Windows). The previous checkpoint stays readable as
``<name>.prev`` until the new one is in place.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import random
import shutil
import uuid
import warnings
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

log = logging.getLogger(__name__)

CHECKPOINT_FILE = "checkpoint.pt"  # a training run's checkpoint in its run dir
PREV_SUFFIX = ".prev"
DAMAGED_SUFFIX = ".damaged"  # an unreadable checkpoint set aside by a resume
PROBE_BYTES = 1 << 16  # what `check_writable` writes: more than a full disk takes

# What torch.load raises on a truncated or otherwise damaged file (a zip archive cut near its
# start gives OSError EINVAL).
_UNREADABLE = (
    RuntimeError,
    EOFError,
    pickle.UnpicklingError,
    ValueError,
    zipfile.BadZipFile,
    OSError,
)


class CheckpointError(RuntimeError):
    """A checkpoint file exists but cannot be read (and no readable ``.prev`` exists)."""


class RunWriteError(RuntimeError):
    """A run's file could not be written (no space, no permission, a read-only disk): the
    message names the path and the operating system's reason; the file's previous version
    is left as it was."""


def write_failure(path: Path, err: BaseException) -> RunWriteError:
    """`RunWriteError` for `path`: the OS error's reason, or torch's (a full disk inside
    ``torch.save`` is a RuntimeError "unexpected pos"), the disk and its free space when
    known, and what was kept."""
    coded = isinstance(err, OSError) and err.strerror
    reason = f"{err.strerror} (errno {err.errno})" if coded else str(err)
    reason = reason.splitlines()[0] if reason else type(err).__name__
    if "unexpected pos" in reason:
        reason = f"the file came out short, as on a full disk (torch.save: {reason})"
    try:
        free = shutil.disk_usage(path.parent).free / 2**20
        disk = f"; {free:.1f} MB free on the disk mounted at {_mount_point(path.parent)}"
    except OSError:
        disk = ""
    kept = [p.name for p in (path, prev_path(path)) if p.exists()]
    kept_text = f"kept as they were: {', '.join(kept)}" if kept else "nothing was written"
    return RunWriteError(f"cannot write {path}: {reason}{disk}; {kept_text}")


def _mount_point(folder: Path) -> Path:
    """The mount point of the file system that holds `folder`."""
    folder = folder.resolve()
    while not os.path.ismount(folder) and folder != folder.parent:
        folder = folder.parent
    return folder


def check_writable(folder: Path) -> None:
    """Make `folder` (and its parents) if missing and write `PROBE_BYTES` to a file in it and
    remove it (a full disk fails there, not in the run's first files); a RunWriteError names
    the path and the reason when that fails (a folder it made is removed again)."""
    made = not folder.exists()
    probe = folder / f".write_check.{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as f:
            f.write(bytes(PROBE_BYTES))
            f.flush()
            os.fsync(f.fileno())
        probe.unlink()
    except OSError as err:
        with contextlib.suppress(OSError):
            probe.unlink()
        if made and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        raise write_failure(probe, err) from err


def prev_path(path: str | Path) -> Path:
    """Where the previous version of checkpoint ``path`` is kept."""
    path = Path(path)
    return path.with_name(path.name + PREV_SUFFIX)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX only; a no-op where dirs cannot be opened)."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _keep_previous(path: Path) -> None:
    """Make ``<path>.prev`` a complete copy of ``path`` while ``path`` stays in place."""
    prev = prev_path(path)
    tmp_prev = prev.with_name(f".{prev.name}.{os.getpid()}.tmp")
    try:
        os.link(path, tmp_prev)  # free, and path keeps its name throughout
    except OSError:
        shutil.copyfile(path, tmp_prev)  # file systems without hard links
    try:
        os.replace(tmp_prev, prev)
    finally:
        tmp_prev.unlink(missing_ok=True)


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], None], keep_prev: bool) -> None:
    """Write a file atomically: ``write(f)`` fills a temp file that then replaces ``path``.

    Args:
        path: destination; its folder is created if needed.
        write: called with a binary file object open for writing.
        keep_prev: keep the current content of ``path`` as ``<path>.prev``.

    Raises:
        RunWriteError: the file could not be written (``path`` is left as it was).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # os.open with mode 0o666 honours the umask (mkstemp would make the file owner-only)
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
        with os.fdopen(os.open(tmp, flags, 0o666), "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if keep_prev and path.exists():
            _keep_previous(path)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except (OSError, RuntimeError) as err:  # torch.save reports a full disk as RuntimeError
        raise write_failure(path, err) from err
    finally:
        tmp.unlink(missing_ok=True)


def _writer_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temps(folder: Path) -> list[Path]:
    """Remove the temporary files that a killed writer left in `folder` (``.<name>.<pid>.*tmp``
    of `atomic_write` and `_keep_previous` whose process is gone). -> the files removed."""
    removed = []
    for tmp in folder.glob(".*.tmp"):
        pid = next((int(part) for part in tmp.name.split(".") if part.isdigit()), None)
        if pid is not None and pid != os.getpid() and not _writer_alive(pid):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    if removed:
        names = ", ".join(p.name for p in removed)
        log.info("removed the temporary files of a killed writer: %s", names)
    return removed


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Save ``state`` with ``torch.save`` atomically, keeping the previous file as ``.prev``.

    To load with ``weights_only=True`` (the default of ``load_checkpoint``) the state should
    hold only tensors, plain Python containers and scalars (``rng_state()`` output qualifies).
    """
    atomic_write(path, lambda f: torch.save(state, f), keep_prev=True)
    log.debug("saved checkpoint %s", path)


def _load(path: Path, map_location: str | torch.device | None, weights_only: bool) -> dict:
    state = torch.load(path, map_location=map_location, weights_only=weights_only)
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(state).__name__}, not a dict")
    return state


def load_checkpoint(
    path: str | Path,
    map_location: str | torch.device | None = "cpu",
    weights_only: bool = True,
    set_aside: bool = False,
) -> dict[str, Any]:
    """Load a checkpoint written by ``save_checkpoint``.

    Falls back to ``<path>.prev`` with a warning when ``path`` is unreadable or missing (a
    resume that set it aside). With `set_aside` (a resume that will save again) the
    unreadable ``path`` is renamed to ``<path>.damaged``, named in the warning, so that the
    next save keeps the good ``.prev`` as the backup instead of the damaged file.

    Raises:
        FileNotFoundError: neither ``path`` nor its ``.prev`` exists.
        CheckpointError: neither ``path`` nor its ``.prev`` can be read.
    """
    path = Path(path)
    prev = prev_path(path)
    if not path.is_file():
        if not prev.is_file():
            raise FileNotFoundError(f"checkpoint file {path} does not exist")
        log.warning("checkpoint %s is missing; loading the previous one %s", path, prev)
        return _load_previous(path, prev, map_location, weights_only, "missing")
    try:
        return _load(path, map_location, weights_only)
    except _UNREADABLE as err:
        main_error, main_why = err, _why(path, err)
    if not prev.is_file():
        raise CheckpointError(
            f"cannot read checkpoint {path} ({main_why}) and no previous version {prev} exists"
        ) from main_error
    state = _load_previous(path, prev, map_location, weights_only, main_why)
    aside = ""
    if set_aside:
        damaged = path.with_name(path.name + DAMAGED_SUFFIX)
        os.replace(path, damaged)
        aside = f"; the damaged file is kept as {damaged}"
    log.warning(
        "checkpoint %s is unreadable (%s); loaded the previous one %s%s",
        path, main_why, prev, aside,
    )  # fmt: skip
    return state


def _load_previous(
    path: Path, prev: Path, map_location: str | torch.device | None, weights_only: bool,
    main_why: str,
) -> dict[str, Any]:  # fmt: skip
    try:
        return _load(prev, map_location, weights_only)
    except _UNREADABLE as err:
        raise CheckpointError(
            f"cannot read checkpoint {path} ({main_why}) "
            f"nor its previous version {prev} ({_why(prev, err)})"
        ) from err


def _why(path: Path, err: BaseException) -> str:
    """What is wrong with an unreadable checkpoint: its size and torch's error, first line."""
    reason = (str(err).splitlines() or [type(err).__name__])[0]
    return f"damaged or cut short, {path.stat().st_size:,} bytes: {reason}"


def _numpy_state() -> dict[str, Any]:
    name, key, pos, has_gauss, cached = np.random.get_state(legacy=True)
    return {
        "name": name,
        "key": torch.from_numpy(key.astype(np.int64)),
        "pos": int(pos),
        "has_gauss": int(has_gauss),
        "cached_gaussian": float(cached),
    }


def _set_numpy_state(state: Mapping[str, Any]) -> None:
    key = state["key"].numpy().astype(np.uint32)
    np.random.set_state(
        (state["name"], key, state["pos"], state["has_gauss"], state["cached_gaussian"])
    )


def rng_state(generators: Mapping[str, torch.Generator] | None = None) -> dict[str, Any]:
    """Snapshot of every random number generator a run uses.

    Args:
        generators: named ``torch.Generator`` objects (e.g. the planner's, the fit's) whose
            states are included.

    Returns:
        A dict of tensors and plain Python values (loadable with ``weights_only=True``).
    """
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
    return {
        "torch": torch.get_rng_state(),
        "cuda": cuda,
        "numpy": _numpy_state(),
        "python": random.getstate(),
        "generators": {name: g.get_state() for name, g in (generators or {}).items()},
    }


def _set_cuda_state(states: list[torch.Tensor] | None) -> None:
    if states is None:
        return
    if not torch.cuda.is_available():
        warnings.warn(
            "checkpoint has CUDA RNG states but CUDA is unavailable; they are ignored", stacklevel=3
        )
        return
    if len(states) != torch.cuda.device_count():
        warnings.warn(
            f"checkpoint has {len(states)} CUDA RNG states for {torch.cuda.device_count()} "
            "devices; restoring the common ones",
            stacklevel=3,
        )
    for device, state in enumerate(states[: torch.cuda.device_count()]):
        torch.cuda.set_rng_state(state, device)


def set_rng_state(
    state: Mapping[str, Any], generators: Mapping[str, torch.Generator] | None = None
) -> None:
    """Restore a snapshot made by ``rng_state``.

    Raises ``KeyError`` when a generator in ``generators`` has no saved state.
    """
    torch.set_rng_state(state["torch"])
    _set_cuda_state(state.get("cuda"))
    _set_numpy_state(state["numpy"])
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    saved = state.get("generators", {})
    for name, generator in (generators or {}).items():
        if name not in saved:
            raise KeyError(f"no saved state for generator {name!r}; saved: {sorted(saved)}")
        generator.set_state(saved[name])
