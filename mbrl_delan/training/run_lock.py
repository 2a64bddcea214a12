"""One writer per run folder: an advisory lock (``fcntl.flock``) on ``<run dir>/.lock``.

The operating system releases the lock when its holder exits, however it ends (a kill
included), so a crashed run never leaves its folder locked. The lock file keeps the holder's
pid for the message a second writer gets. Where ``fcntl`` is missing (Windows) the lock is a
no-op.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

LOCK_FILE = ".lock"


class RunLockedError(RuntimeError):
    """Another live process holds the run folder's lock; the message names it and its pid."""


class RunLock:
    """The lock of run folder `folder`, held from `acquire` until `release` or exit."""

    def __init__(self, folder: Path) -> None:
        self.path = Path(folder) / LOCK_FILE
        self._file: IO[str] | None = None

    def acquire(self) -> None:
        """Take the lock without waiting. Raises RunLockedError when another process has it."""
        if fcntl is None or self._file is not None:
            return
        handle = open(self.path, "a+", encoding="utf-8")  # noqa: SIM115 - held while running
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "unknown"
            handle.close()
            raise RunLockedError(
                f"run dir {self.path.parent} is in use by another process (pid {holder}): "
                "one train, resume or fit writes a run dir at a time; wait for it to end"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self._file = handle

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing the file releases the lock
            self._file = None
