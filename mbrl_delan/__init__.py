"""mbrl_delan: model-based RL on TorchRL with Deep Lagrangian Networks as the world model.

Importing `mbrl_delan.envs` registers a gymnasium id for each registered env
(`mbrl_delan.envs.gym_id`, e.g. ``gym.make("mbrl_delan/Pendulum-v0")``); the envs load only
when made.
"""

import os
import sys
from types import TracebackType

__version__ = "0.1.0"

EXIT_INTERRUPTED = 130  # a process stopped by Ctrl-C (SIGINT), as a shell reports it


def _interrupted_while_starting(
    kind: type[BaseException],
    value: BaseException,
    traceback: TracebackType | None,
    previous=sys.excepthook,  # noqa: ANN001 (the hook before this one)
) -> None:
    """Ctrl-C before an entry point's own handling began (its imports take seconds): one
    line, not a traceback; any other error as before."""
    if issubclass(kind, KeyboardInterrupt):
        sys.stderr.write("stopped (Ctrl-C) while starting: nothing was written\n")
        sys.stderr.flush()  # before Python ends itself by SIGINT
        return
    previous(kind, value, traceback)


def _starting_an_entry_point() -> bool:
    """Whether this import is an entry point's start: ``python -m mbrl_delan.<module>``
    (Python names the program ``-m`` while it imports the module's package) or an
    ``mbrl-delan-*`` console script."""
    program = os.path.basename(sys.argv[0]) if sys.argv else ""
    return program == "-m" or program.startswith("mbrl-delan")


if _starting_an_entry_point():
    sys.excepthook = _interrupted_while_starting
