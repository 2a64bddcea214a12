"""The package's floors: every folder (and top-level module) sits on a floor of `FLOORS`
and imports nothing from a higher one; the entry points (`train`, `fit`, `bench`,
`rescore`) sit on top, nothing below imports them; the config floor (`schema`) does not
reach up into the benchmarks; the modules' top-level imports form no cycle. Read from the
source (AST), so a lazy (function-level) import counts too for the floors, and only
top-level ones for cycles (those run at import time)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mbrl_delan"
ENTRY_POINTS = {"mbrl_delan.train", "mbrl_delan.fit", "mbrl_delan.bench", "mbrl_delan.rescore"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}

# bottom to top: a module may import from its own floor and the ones below (a folder's
# modules share its floor; "" is the package's __init__)
FLOORS = (
    ("", "keys", "rules", "registry", "figure_style", "configs", "provenance"),
    ("systems",),
    ("tasks",),
    ("models",),
    ("accelerate",),
    ("objectives",),
    ("planners",),
    ("data",),
    ("training",),
    ("envs",),
    ("conf",),
    ("runs", "sweep", "report", "fit_report", "evaluate", "rescore"),
    ("benchmarks",),
    ("train", "fit", "bench"),
)
FLOOR = {name: level for level, names in enumerate(FLOORS) for name in names}


def _place(module: str) -> str:
    """The folder or top-level module `module` belongs to ("" for the package itself)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


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


def test_every_folder_is_on_a_floor() -> None:
    assert sorted({_place(name) for name in MODULES} - set(FLOOR)) == []


def test_no_module_imports_from_a_higher_floor() -> None:
    upward = sorted(
        (name, imported)
        for name, path in MODULES.items()
        for imported in _imports(path, top_level_only=False)
        if FLOOR[_place(imported)] > FLOOR[_place(name)]
    )
    assert upward == []


def test_the_registries_import_nothing_of_the_package() -> None:
    """The registries are the bottom floor: a plugin's env, model or planner registers
    there without importing the config code, and `mbrl_delan.conf.registry` is the same."""
    import mbrl_delan.conf.registry as conf_registry
    import mbrl_delan.registry as registry

    assert _imports(MODULES["mbrl_delan.registry"], top_level_only=False) == set()
    assert conf_registry.register_env is registry.register_env
    assert conf_registry.PLANNERS is registry.PLANNERS


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
