"""The package's floors: the entry points (`train`, `fit`, `bench`, `rescore`) sit on top,
nothing below imports them; the config floor (`schema`) does not reach up into the
benchmarks; the modules' top-level imports form no cycle. Read from the source (AST), so a
lazy import counts too for the floors, and only top-level ones for cycles (those run at
import time)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mbrl_delan"
ENTRY_POINTS = {"mbrl_delan.train", "mbrl_delan.fit", "mbrl_delan.bench", "mbrl_delan.rescore"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _imports(path: Path, top_level_only: bool) -> set[str]:
    """The package modules `path` imports (`from mbrl_delan import x` counts as module x)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else ast.walk(tree)
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in found if name in MODULES}


def test_nothing_below_the_entry_points_imports_them() -> None:
    upward = {
        name: sorted(_imports(path, top_level_only=False) & ENTRY_POINTS)
        for name, path in MODULES.items()
        if name not in ENTRY_POINTS
    }
    assert {name: up for name, up in upward.items() if up} == {}


def test_the_schemas_do_not_import_the_benchmarks() -> None:
    imported = _imports(MODULES["mbrl_delan.conf.schema"], top_level_only=False)
    assert not [name for name in imported if name.startswith("mbrl_delan.benchmarks")]


def test_top_level_imports_form_no_cycle() -> None:
    graph = {name: _imports(path, top_level_only=True) - {name} for name, path in MODULES.items()}
    done: set[str] = set()

    def visit(name: str, path: list[str]) -> list[str] | None:
        if name in path:
            return path[path.index(name) :] + [name]
        if name in done:
            return None
        for child in sorted(graph.get(name, ())):
            cycle = visit(child, [*path, name])
            if cycle:
                return cycle
        done.add(name)
        return None

    cycles = [c for name in sorted(graph) if (c := visit(name, []))]
    assert cycles == [], " -> ".join(cycles[0])
