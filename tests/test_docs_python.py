"""The Python examples of docs/torchrl.md run as written, one after the other in one
namespace (the second plans with the model the first fitted), in a scratch folder that stays
empty; TorchRL's MPPI and CEM on the fitted DeLaN reach the page's bar, 0.6 of the project's
MPPI over a 100-step pendulum episode."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "torchrl.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


@pytest.mark.slow
@pytest.mark.heavy
def test_the_torchrl_page_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    blocks = python_blocks(PAGE.read_text(encoding="utf-8"))
    assert len(blocks) == 2
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(PAGE), "exec"), namespace)  # noqa: S102 - the docs' own code
    out = capsys.readouterr().out
    assert re.search(r"round 2: return [\d.]+, oracle [\d.]+, \d+ env steps", out), out
    assert "['q', 'qd']" in out, out
    row = r"(TorchRL's \w+) on the DeLaN: return [\d.]+ over 100 steps, ([\d.]+) of"
    ratios = dict(re.findall(row, out))
    assert set(ratios) == {"TorchRL's MPPI", "TorchRL's CEM"}, out
    assert all(float(r) >= 0.6 for r in ratios.values()), out  # the page's bar
    zero = float(re.search(r"zero torque: ([\d.]+)", out).group(1))
    assert zero < 1.0, out  # hanging still scores about 0: the planners' returns are earned
    assert list(tmp_path.iterdir()) == []  # the page says: nothing is written
