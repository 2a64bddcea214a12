"""Where a figure comes from: the command that made it, the code's commit and the host.

Every run's ``summary.json`` (train and fit) and every bench record carry `provenance`:

- ``command``: the command line as the user typed it (the console script's name, or
  ``python -m <module>``, then the arguments, shell-quoted);
- ``git_commit``: the commit of the package's git checkout (None for an installed wheel or
  without git), and ``dirty``: whether its tracked files differ from that commit;
- ``host``: the CPU's model name, its CPU count, torch's intra-op threads and the 1-minute
  load average when the command started (`started_host`): a timing beside a load of 2 on
  2 cores was measured on a busy host.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
from functools import cache
from pathlib import Path
from typing import Any

import torch

PACKAGE_DIR = Path(__file__).resolve().parent


def cpu_name() -> str:
    """The CPU model name (from /proc/cpuinfo on Linux, else `platform.processor()`)."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def program_name(module: str) -> str:
    """How the user called a command-line tool: its console script's name
    (``mbrl-delan-evaluate``), else ``python -m <module>``."""
    called = Path(sys.argv[0]).name
    return called if called.startswith("mbrl-delan-") else f"python -m {module}"


def command_line(module: str) -> str | None:
    """The command as typed, `program_name` then the arguments, shell-quoted; None when the
    process is not that command (`module` called from Python: a test, a notebook)."""
    called, name = Path(sys.argv[0]), module.rsplit(".", 1)[-1]
    if called.name != f"mbrl-delan-{name}" and called.resolve() != PACKAGE_DIR / f"{name}.py":
        return None
    return shlex.join([*program_name(module).split(), *sys.argv[1:]])


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], cwd=PACKAGE_DIR, capture_output=True, text=True,
                              timeout=10, check=False)  # fmt: skip
    except (OSError, subprocess.SubprocessError):  # no git, or it hung
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@cache
def code_version() -> dict[str, Any]:
    """``git_commit`` and ``dirty`` of the package's checkout (None, None outside one)."""
    commit = _git("rev-parse", "HEAD")
    if commit is None:
        return {"git_commit": None, "dirty": None}
    status = _git("status", "--porcelain", "--untracked-files=no", "--", str(PACKAGE_DIR))
    return {"git_commit": commit, "dirty": bool(status) if status is not None else None}


@cache
def started_host() -> dict[str, Any]:
    """The host when first asked (a command asks at its start): CPU, CPUs, threads, load."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return {"cpu": cpu_name(), "cpus": os.cpu_count(), "threads": torch.get_num_threads(),
            "load_1min": load}  # fmt: skip


def provenance(module: str) -> dict[str, Any]:
    """``command``, ``git_commit``, ``dirty`` and ``host`` (module docstring)."""
    return {"command": command_line(module), **code_version(), "host": started_host()}
