"""The Python examples of docs/torchrl.md run as written, one after the other in one
namespace (the second plans with the model the first fitted), in a scratch folder that stays
empty."""

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
    assert "TorchRL's MPPI on the DeLaN: return" in out and "['q', 'qd']" in out, out
    assert list(tmp_path.iterdir()) == []  # the page says: nothing is written
