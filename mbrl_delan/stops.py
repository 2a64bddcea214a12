"""The line that ends a command: ``<kind>: <what>`` on standard error, one format everywhere.

Every entry point (train, fit, bench, evaluate, rescore, report) ends a run it cannot do, or
one stopped by Ctrl-C, with one such line: `kind` says what went wrong (``config error``,
``bad data file``, ``cannot resume``, ``stopped (Ctrl-C)``, ...), `what` names the value, file
or run and, where one exists, the fix or the resume command. The console's progress log
(standard output under Hydra) does not repeat it; the run's log file (``train.log``,
``fit.log``) keeps it, as does any other non-console logging handler (pytest's caplog).
"""

from __future__ import annotations

import logging
import sys
from typing import NoReturn

log = logging.getLogger(__name__)

STOPPED = "stopped (Ctrl-C)"  # the kind of a run the user stopped


def _is_console(handler: logging.Handler) -> bool:
    stream = getattr(handler, "stream", None)
    return stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__)


def stop_line(kind: str, what: object, level: int = logging.ERROR) -> str:
    """Write ``<kind>: <what>`` to standard error and to the root logger's non-console
    handlers (the run's log file) at `level`; the line is returned."""
    line = f"{kind}: {what}"
    record = log.makeRecord(log.name, level, __file__, 0, line, None, None)
    for handler in logging.getLogger().handlers:
        if not _is_console(handler) and level >= handler.level:
            handler.handle(record)
    sys.stderr.write(line + "\n")
    sys.stderr.flush()
    return line


def stop(kind: str, what: object, code: int = 2) -> NoReturn:
    """`stop_line(kind, what)`, then exit with `code` (2: the input; 1: the run failed)."""
    stop_line(kind, what)
    sys.exit(code)
