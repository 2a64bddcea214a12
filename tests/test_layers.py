"""The package's places and what each builds on: every folder (and top-level module) is a
place of `DEPENDS` (or of the bottom floor, `BOTTOM`) and imports only from the places it
builds on, directly or through them, never from a sibling; the entry points (`train`, `fit`,
`bench`, `rescore`) sit on top, nothing below imports them; the config floor (`schema`) does
not reach up into the benchmarks; the modules' top-level imports form no cycle. Read from the
source (AST), so a lazy (function-level) import and an import by name (a string naming a
package module) count too for the places, and only top-level ones for cycles (those run at
import time). docs/architecture.md draws the same table."""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mbrl_delan"
ENTRY_POINTS = {"mbrl_delan.train", "mbrl_delan.fit", "mbrl_delan.bench", "mbrl_delan.rescore"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}

# the bottom floor: every place may import it, it imports nothing above it
BOTTOM = (
    "", "keys", "rules", "stops", "registry", "figure_style", "configs", "provenance", "intervals",
)  # fmt: skip
# each other place (a folder, or a top-level module) and the places it builds on directly; it
# may import those and what they build on, never a sibling it does not name (data and models
# are siblings: neither imports the other). docs/architecture.md's table is this one.
DEPENDS: dict[str, tuple[str, ...]] = {
    "systems": (),
    "tasks": ("systems",),
    "models": ("systems",),
    "data": ("systems",),
    "accelerate": ("models",),
    "objectives": ("tasks", "accelerate"),
    "planners": ("objectives",),
    "training": ("objectives", "data"),
    "envs": ("training",),
    "conf": ("planners", "envs"),
    "runs": ("conf",),
    "sweep": ("conf",),
    "report": ("sweep",),
    "fit_report": ("report",),
    "evaluate": ("runs",),
    "rescore": ("evaluate",),
    "fit_run": ("conf",),
    "benchmarks": ("runs", "fit_run"),
    "train": ("runs", "sweep"),
    "fit": ("runs", "sweep", "fit_run"),
    "bench": ("benchmarks",),
}
PLACES = (*BOTTOM, *DEPENDS)
# a string naming a package module's attribute, as an import by name does ("module:attr")
MODULE_STRING = re.compile(r"^(mbrl_delan(?:\.\w+)*):\w+$")


def foundations(place: str) -> set[str]:
    """What `place` may import: itself, the bottom floor and, transitively, what it builds on."""
    if place in BOTTOM:
        return set(BOTTOM)
    found = {place, *BOTTOM}
    for below in DEPENDS[place]:
        found |= foundations(below)
    return found


def _place(module: str) -> str:
    """The folder or top-level module `module` belongs to ("" for the package itself)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _imports(path: Path, top_level_only: bool) -> set[str]:
    """The package modules `path` imports (`from mbrl_delan import x` counts as module x);
    beyond the top level, a string that names a module counts too (an import by name)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else ast.walk(tree)
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if match := MODULE_STRING.match(node.value):
                found.add(match.group(1))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "import_module":
            if node.args and isinstance(node.args[0], ast.Constant):
                found.add(str(node.args[0].value))
    return {name for name in found if name in MODULES}


def test_every_folder_is_a_place() -> None:
    assert sorted({_place(name) for name in MODULES} - set(PLACES)) == []


def test_every_import_is_of_what_its_place_builds_on() -> None:
    """No module imports from a place its own does not build on: not from above, not from
    a sibling (function-level imports and imports by name included: ``"module:attr"``
    strings and ``import_module("module")``)."""
    stray = sorted(
        (name, imported)
        for name, path in MODULES.items()
        for imported in _imports(path, top_level_only=False)
        if _place(imported) not in foundations(_place(name))
    )
    assert stray == []


def test_each_named_foundation_is_used() -> None:
    """The table is the code's graph, not a looser one: each place imports from every place
    it names as a direct foundation."""
    used = {place: set() for place in DEPENDS}
    for name, path in MODULES.items():
        if _place(name) in used:
            used[_place(name)] |= {_place(i) for i in _imports(path, top_level_only=False)}
    unused = {p: sorted(set(below) - used[p]) for p, below in DEPENDS.items()}
    assert {p: u for p, u in unused.items() if u} == {}


def test_the_architecture_page_draws_the_same_graph() -> None:
    """docs/architecture.md's table of places (``| `place` | `a`, `b` |``) is `DEPENDS`."""
    text = (PACKAGE.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| `(\w+)` \|(.*)\|$", text.split("## Floors", 1)[1], re.M)
    drawn = {place: tuple(re.findall(r"`(\w+)`", below)) for place, below in rows}
    assert drawn == DEPENDS


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
