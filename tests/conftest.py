"""Test-session settings and the in-process command runner."""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable

import pytest
import torch
from hydra.core.global_hydra import GlobalHydra


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked heavy first: a worker starts on them while the other runs the rest."""
    items.sort(key=lambda item: item.get_closest_marker("heavy") is None)


# Set for the test session and the commands its tests start. wandb's console capture patches
# the process's standard streams while pytest captures them; torch.compile's default pool of
# compile subprocesses, one per worker on a 2-core machine, oversubscribes the cores and holds
# pipes beside pytest's capture files. Either was suspected when pytest's capture file of one
# worker was found closed and every later test of that worker failed at set-up.
TEST_ENVIRONMENT = {"WANDB_CONSOLE": "off", "TORCHINDUCTOR_COMPILE_THREADS": "1"}


@pytest.fixture(autouse=True, scope="session")
def quiet_environment():
    """`TEST_ENVIRONMENT` for the session (and torch.compile compiling in this process)."""
    import torch._inductor.config as inductor

    previous = {k: os.environ.get(k) for k in TEST_ENVIRONMENT}
    threads = inductor.compile_threads
    os.environ.update(TEST_ENVIRONMENT)
    inductor.compile_threads = 1
    yield
    inductor.compile_threads = threads
    for key, value in previous.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture(autouse=True, scope="session")
def one_torch_thread():
    """Tiny tensors: one intra-op thread is faster, and immune to a busy machine's other cores."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def run_main(
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> Callable[..., tuple[int, str]]:
    """Run an entry point's ``main`` in this process as its command would: ``run_main(main,
    *args)`` -> (exit code, everything it printed and logged). Hydra finds the config folder
    from the entry point's file, as with ``python -m``; its logging set-up is undone after."""
    root, handlers, level = logging.getLogger(), logging.getLogger().handlers[:], logging.root.level
    monkeypatch.setenv("HYDRA_MAIN_MODULE", "__main__")

    def run(main: Callable[[], object], *args: str) -> tuple[int, str]:
        GlobalHydra.instance().clear()
        monkeypatch.setattr(sys, "argv", ["main", *args])
        try:
            main()
            code = 0
        except SystemExit as exit_:
            code = exit_.code if isinstance(exit_.code, int) else 1
        finally:
            GlobalHydra.instance().clear()
            root.handlers[:] = handlers
            root.setLevel(level)
        out = capsys.readouterr()
        text = out.out + out.err + caplog.text
        caplog.clear()
        return code, text

    return run
