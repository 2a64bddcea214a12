"""Test-session settings and the in-process command runner."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable

import pytest
import torch
from hydra.core.global_hydra import GlobalHydra


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked heavy first: a worker starts on them while the other runs the rest."""
    items.sort(key=lambda item: item.get_closest_marker("heavy") is None)


@pytest.fixture(autouse=True, scope="session")
def absl_logs_to_the_real_stderr():
    """absl's log handler (absl-py comes with dm-control) writes to the sys.stderr of the
    moment absl is imported, under pytest a capture file, and closes that stream whenever
    logging is configured again unless it is one of the standard streams of that moment:
    Hydra configures logging in the in-process entry-point tests, and with capsys active
    there it closed pytest's capture file, so every later test of that worker failed at
    set-up. Its stream is made the real stderr, which it never closes."""
    try:
        from absl import logging as absl_logging
    except ImportError:  # absl-py missing: nothing to guard
        yield
        return
    handler = absl_logging.get_absl_handler().python_handler
    stream, handler.stream = handler.stream, sys.__stderr__
    yield
    handler.stream = stream


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
