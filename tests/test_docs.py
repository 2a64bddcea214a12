"""The docs cannot drift from the code.

- Every `python -m mbrl_delan.<entry point>` command in README.md and docs/**/*.md (fenced
  code blocks and inline code) is checked against its entry point: Hydra overrides are
  composed with the entry point's config tree (every value of a `-m` sweep) and passed through
  the entry point's own config validation; argparse arguments are parsed by its parser.
- Every key of every file under mbrl_delan/configs/ is listed in docs/configuration.md.
- Every page under docs/ is in the mkdocs nav, and `mkdocs build --strict` succeeds.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib.util
import io
import itertools
import math
import re
import shlex
import subprocess
import sys
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from unittest import mock

import mujoco
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig

from mbrl_delan import bench, evaluate, fit_report, report, rescore
from mbrl_delan.benchmarks import figures, fit_arrays, own_arm, robust
from mbrl_delan.conf.builders import build_model, build_planner
from mbrl_delan.conf.checks import DTYPES, validate_train_config
from mbrl_delan.conf.fitting import validate_fit_config
from mbrl_delan.conf.inverse import InverseContext, build_inverse_model
from mbrl_delan.data.mocap.retarget import joint_layout
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.systems.external import humanoid_cmu_xml
from mbrl_delan.systems.system import System

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
DOC_FILES = [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]
CONFIGS = REPO / "mbrl_delan" / "configs"
SCRIPTS = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]

PACKAGE = "mbrl_delan."
PLACEHOLDER = "PLACEHOLDER"  # stands in for a `<placeholder>` or an undefined `$VAR`
MAX_SWEEP_JOBS = 256


# cmu_track's system does not depend on its clip: build it with the test data's clip, so the
# check needs no download of the clips a doc command names
TEST_CLIP = {"clip": "09_06", "folders": [str(Path(__file__).parent / "data")], "download": False}


@functools.cache
def _env_system(name: str, frame_skip: int | None, episode_len: int | None) -> System:
    options = TEST_CLIP if name == "cmu_track" else None
    return make_env_parts(name, frame_skip, None if options else episode_len, options).system


def check_train_config(cfg: DictConfig) -> None:
    """`train`'s own checks, then its model and planner built (constructor checks)."""
    validate_train_config(cfg)
    system = _env_system(cfg.env.name, cfg.env.frame_skip, cfg.env.episode_len)
    build_model(cfg.model, system)
    build_planner(cfg.planner, system, DTYPES[cfg.dtype])


@functools.cache
def _humanoid_cmu() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))


def check_fit_config(cfg: DictConfig) -> None:
    """`fit`'s own checks, then its model built on humanoid_CMU (the data are not loaded)."""
    validate_fit_config(cfg)
    model = _humanoid_cmu()
    context = InverseContext(joint_layout(model), cfg.loss.std_floor, mj_model=model)
    build_inverse_model(cfg.model, context)


@dataclass(frozen=True)
class HydraEntryPoint:
    config_dir: Path
    config_name: str
    validate: Callable[[DictConfig], Any]  # raises if the entry point would reject the config


HYDRA_ENTRY_POINTS = {
    "mbrl_delan.train": HydraEntryPoint(CONFIGS / "train", "config", check_train_config),
    "mbrl_delan.fit": HydraEntryPoint(CONFIGS / "fit", "config", check_fit_config),
    "mbrl_delan.bench": HydraEntryPoint(CONFIGS / "bench", "config", bench.build_options),
}
ARGPARSE_ENTRY_POINTS: dict[str, Callable[[list[str]], Any]] = {
    "mbrl_delan.report": report.main,  # main(argv) builds its parser and parses argv first
    "mbrl_delan.fit_report": fit_report.main,
    "mbrl_delan.benchmarks.figures": figures.main,
    "mbrl_delan.benchmarks.own_arm": own_arm.main,
    "mbrl_delan.benchmarks.fit_arrays": fit_arrays.main,
    "mbrl_delan.benchmarks.robust": robust.main,
    "mbrl_delan.evaluate": evaluate.main,
    "mbrl_delan.rescore": rescore.main,
}

# Commands in the docs that are not meant to be run as written. Keep this list short.
NOT_CHECKED = {
    "python -m mbrl_delan.fit_report RUN... [--figure PNG] [--table]": (
        "usage synopsis: RUN... and [...] are grammar, not arguments"
    ),
}

# Hydra's own command-line flags (`python -m mbrl_delan.train --cfg job`), value or not.
HYDRA_FLAGS_WITH_VALUE = {"--cfg", "-c", "--package", "-p", "--info", "-i"}
HYDRA_FLAGS = {"--help", "-h", "--hydra-help", "--resolve", "--version"}


# ------------------------------------------------------------------------ extraction


class DocCommandError(AssertionError):
    """A command in the docs that its entry point would reject."""


@dataclass(frozen=True)
class DocCommand:
    """One `python -m mbrl_delan.X ...` command found in a Markdown file."""

    path: Path
    line: int
    text: str  # the command as written (continuations joined)
    module: str  # mbrl_delan.X
    args: tuple[str, ...]  # after `python -m module`, variables and placeholders expanded
    name_only: bool = False  # inline `python -m mbrl_delan.X` alone: names the entry point

    @property
    def where(self) -> str:
        try:
            name = self.path.relative_to(REPO)
        except ValueError:
            name = self.path
        return f"{name}:{self.line}: {self.text}"


FENCE = re.compile(r"^\s*(`{3,}|~{3,})")
ASSIGNMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)=(.*)$")
VARIABLE = re.compile(r"\$(?:\{([A-Za-z_][A-Za-z0-9_]*)\}|([A-Za-z_][A-Za-z0-9_]*))")
ANGLE_PLACEHOLDER = re.compile(r"<[^<>\s][^<>]*>")
REDIRECTS = {">", ">>", "<", ">&", "&>", "<<"}


def _tokens(text: str) -> list[str]:
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    lexer.commenters = "#"
    return list(lexer)


def _segments(tokens: list[str]) -> list[list[str]]:
    """Simple commands of a token list: split at `;`, `&&`, `|`, ...; redirections dropped."""
    segments: list[list[str]] = [[]]
    skip_next = False
    for token in tokens:
        if skip_next:
            skip_next = False
        elif token in REDIRECTS:
            skip_next = True  # and its target
        elif token and set(token) <= set("();&|<>"):
            segments.append([])
        else:
            segments[-1].append(token)
    return [s for s in segments if s]


def _expand(tokens: list[str], variables: dict[str, str]) -> list[str]:
    """`$VAR` / `${VAR}` from the block's assignments; a bare `$VAR` is re-split into words
    (as the shell does unquoted). Undefined variables become PLACEHOLDER."""

    def value(match: re.Match[str]) -> str:
        return variables.get(match.group(1) or match.group(2), PLACEHOLDER)

    out: list[str] = []
    for token in tokens:
        if VARIABLE.fullmatch(token):
            out.extend(value(VARIABLE.fullmatch(token)).split())  # type: ignore[arg-type]
        else:
            out.append(VARIABLE.sub(value, token))
    return out


def _assignments(segment: list[str]) -> dict[str, str] | None:
    """`NAME=value ...` or `export NAME=value ...` alone in a command: the variables set."""
    words = segment[1:] if segment[0] == "export" else segment
    found = [ASSIGNMENT.match(w) for w in words]
    if not words or not all(found):
        return None
    return {m.group(1): m.group(2) for m in found if m}


def _commands_in_tokens(
    tokens: list[str], variables: dict[str, str]
) -> Iterator[tuple[str, list[str]]]:
    """(module, args) of each `python -m mbrl_delan.X ...` in a shell token list, in order;
    also inside a quoted argument (`sbatch --wrap "python -m ..."`). Assignments update
    `variables` as they are met."""
    for segment in _segments(tokens):
        assigned = _assignments(segment)
        if assigned is not None:
            for name, raw in assigned.items():
                variables[name] = " ".join(_expand([raw], variables))
            continue
        words = _expand(segment, variables)
        for i, word in enumerate(words):
            if (
                word in ("python", "python3")
                and words[i + 1 : i + 2] == ["-m"]
                and words[i + 2 : i + 3]
                and words[i + 2].startswith(PACKAGE)
            ):
                # `...` stands for "more of the same" in the docs: not an argument
                yield words[i + 2], [a for a in words[i + 3 :] if a != "..."]
                break
            if word in SCRIPTS:  # a console script: mbrl-delan-train -> mbrl_delan.train
                yield SCRIPTS[word].split(":")[0], [a for a in words[i + 1 :] if a != "..."]
                break
            if f"python -m {PACKAGE}" in word:
                yield from _commands_in_tokens(_tokens(word), variables)
                break


def _logical_lines(lines: list[str], first: int) -> Iterator[tuple[int, str]]:
    """Lines joined at trailing backslashes, with the number of each one's first line."""
    buffer, start = "", first
    for offset, line in enumerate(lines):
        if not buffer:
            start = first + offset
        stripped = line.rstrip()
        if stripped.endswith("\\"):
            buffer += stripped[:-1] + " "
            continue
        yield start, (buffer + line).strip()
        buffer = ""
    if buffer:
        yield start, buffer.strip()


def _block_commands(path: Path, lines: list[str], first: int) -> Iterator[DocCommand]:
    variables: dict[str, str] = {}  # shell variables assigned earlier in the block
    for number, raw in _logical_lines(lines, first):
        line = raw[2:] if raw.startswith("$ ") else raw
        try:
            tokens = _tokens(ANGLE_PLACEHOLDER.sub(PLACEHOLDER, line))
        except ValueError as err:  # not shell (unbalanced quotes): fine unless a command
            if f"python -m {PACKAGE}" in line:
                raise DocCommandError(f"{path}:{number}: cannot split {line!r}: {err}") from err
            continue
        text = " ".join(line.split(" #", 1)[0].split())
        for module, args in _commands_in_tokens(tokens, variables):
            yield DocCommand(path, number, text, module, tuple(args))


def _inline_commands(path: Path, text: str) -> Iterator[DocCommand]:
    """Inline code spans (they may wrap over lines within a paragraph)."""
    for match in re.finditer(r"(?<!`)`([^`]+)`(?!`)", text):
        span = " ".join(match.group(1).split())
        if "\n\n" in match.group(1) or not span.startswith(f"python -m {PACKAGE}"):
            continue
        number = text.count("\n", 0, match.start()) + 1
        tokens = _tokens(ANGLE_PLACEHOLDER.sub(PLACEHOLDER, span))
        for module, args in _commands_in_tokens(tokens, {}):
            yield DocCommand(path, number, span, module, tuple(args), name_only=not args)


def extract_commands(path: Path, text: str | None = None) -> list[DocCommand]:
    """Every `python -m mbrl_delan.X` command of a Markdown file, fenced or inline."""
    lines = (path.read_text(encoding="utf-8") if text is None else text).splitlines()
    commands: list[DocCommand] = []
    prose: list[str] = []  # the text outside fences, fenced lines blanked (keeps numbering)
    fence: str | None = None
    block: list[str] = []
    block_start = 0
    for number, line in enumerate(lines, start=1):
        match = FENCE.match(line)
        if fence is None and match:
            fence, block, block_start = match.group(1), [], number + 1
            prose.append("")
        elif fence is not None and match and match.group(1).startswith(fence):
            commands.extend(_block_commands(path, block, block_start))
            fence = None
            prose.append("")
        elif fence is not None:
            block.append(line)
            prose.append("")
        else:
            prose.append(line)
    commands.extend(_inline_commands(path, "\n".join(prose)))
    return sorted(commands, key=lambda c: c.line)


# ------------------------------------------------------------------------ validation


def _hydra_jobs(args: tuple[str, ...]) -> tuple[str | None, list[list[str]]]:
    """Split Hydra's flags from the overrides; expand `-m` sweeps into one override list per
    job: all combinations, as Hydra's basic sweeper runs them, or, beyond MAX_SWEEP_JOBS, every
    value of each swept key once (the others at their first value). -> (config name, jobs)."""
    multirun, config_name, overrides = False, None, []
    it = iter(args)
    for arg in it:
        if arg in ("-m", "--multirun"):
            multirun = True
        elif arg in ("--config-name", "-cn"):
            config_name = next(it, None)
        elif arg.startswith("--config-name="):
            config_name = arg.split("=", 1)[1]
        elif arg in HYDRA_FLAGS_WITH_VALUE:
            next(it, None)
        elif arg in HYDRA_FLAGS:
            continue
        elif arg.startswith("-"):
            raise DocCommandError(f"unknown Hydra flag {arg!r}")
        else:
            overrides.append(arg)
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except Exception as err:  # noqa: BLE001 - Hydra's parser raises several error types
        raise DocCommandError(f"overrides do not parse: {err}") from err
    choices: list[list[str]] = []
    for override in parsed:
        if override.is_sweep_override():
            if not multirun:
                raise DocCommandError(
                    f"{override.input_line!r} sweeps over values but the command has no -m"
                )
            key = override.get_key_element()
            choices.append([f"{key}={value}" for value in override.sweep_string_iterator()])
        else:
            choices.append([override.input_line])
    if math.prod(len(c) for c in choices) <= MAX_SWEEP_JOBS:
        return config_name, [list(job) for job in itertools.product(*choices)]
    first = [c[0] for c in choices]
    jobs = {tuple(first[:k] + [v] + first[k + 1 :]) for k, c in enumerate(choices) for v in c}
    return config_name, [list(job) for job in sorted(jobs)]


@contextlib.contextmanager
def _cuda_claimed() -> Iterator[None]:
    """Let `device=cuda` in the docs pass the device check on a machine without a GPU."""
    available = torch.cuda.is_available
    torch.cuda.is_available = lambda: True  # type: ignore[assignment]
    try:
        yield
    finally:
        torch.cuda.is_available = available  # type: ignore[assignment]


def check_hydra_command(command: DocCommand) -> None:
    entry = HYDRA_ENTRY_POINTS[command.module]
    config_name, jobs = _hydra_jobs(command.args)
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(entry.config_dir), version_base="1.3"):
        for overrides in jobs:
            try:
                cfg = compose(config_name=config_name or entry.config_name, overrides=overrides)
            except Exception as err:  # noqa: BLE001 - Hydra raises several error types
                raise DocCommandError(f"Hydra rejects {overrides}: {err}") from err
            try:
                with _cuda_claimed():
                    entry.validate(cfg)
            except Exception as err:  # noqa: BLE001 - ConfigError, or a failed lookup
                raise DocCommandError(
                    f"{command.module} rejects {overrides}: {type(err).__name__}: {err}"
                ) from err


class _Parsed(Exception):
    """Raised right after the entry point's parser accepted the arguments: nothing runs."""


def check_argparse_command(command: DocCommand) -> None:
    """Run the entry point's `main(argv)` up to its `parse_args`, and stop there."""
    parse_args = argparse.ArgumentParser.parse_args

    def parse_then_stop(parser: argparse.ArgumentParser, *args: Any, **kwargs: Any) -> Any:
        parse_args(parser, *args, **kwargs)
        raise _Parsed

    stderr = io.StringIO()
    try:
        with (
            mock.patch.object(argparse.ArgumentParser, "parse_args", parse_then_stop),
            contextlib.redirect_stderr(stderr),
            contextlib.redirect_stdout(io.StringIO()),
        ):
            ARGPARSE_ENTRY_POINTS[command.module](list(command.args))
    except _Parsed:
        return
    except SystemExit as exc:
        if exc.code:
            raise DocCommandError(f"arguments do not parse: {stderr.getvalue().strip()}") from exc
        return  # --help
    raise DocCommandError(f"{command.module}.main returned without parsing arguments")


def check_command(command: DocCommand) -> None:
    """Raise DocCommandError (naming the file, line and command) if it would not start."""
    try:
        if command.name_only and command.module in (*HYDRA_ENTRY_POINTS, *ARGPARSE_ENTRY_POINTS):
            return
        if command.module in HYDRA_ENTRY_POINTS:
            check_hydra_command(command)
        elif command.module in ARGPARSE_ENTRY_POINTS:
            check_argparse_command(command)
        else:
            known = sorted([*HYDRA_ENTRY_POINTS, *ARGPARSE_ENTRY_POINTS])
            raise DocCommandError(f"no entry point {command.module}; known: {', '.join(known)}")
    except DocCommandError as err:
        raise DocCommandError(f"{command.where}\n  {err}") from None


# ------------------------------------------------------------------------ the tests

ALL_COMMANDS = [c for path in DOC_FILES for c in extract_commands(path)]
CHECKED = [c for c in ALL_COMMANDS if c.text not in NOT_CHECKED]


def test_docs_hold_commands_for_every_entry_point() -> None:
    modules = {c.module for c in ALL_COMMANDS}
    assert set(HYDRA_ENTRY_POINTS) | set(ARGPARSE_ENTRY_POINTS) <= modules, modules
    unused = set(NOT_CHECKED) - {c.text for c in ALL_COMMANDS}
    assert not unused, f"NOT_CHECKED lists commands no longer in the docs: {unused}"


@pytest.mark.parametrize(
    "command", CHECKED, ids=[f"{c.path.relative_to(REPO)}:{c.line}" for c in CHECKED]
)
def test_doc_command_is_valid(command: DocCommand) -> None:
    check_command(command)


BOGUS = """
Made-up commands, each of which must be rejected.

```bash
python -m mbrl_delan.train model=no_such_model
python -m mbrl_delan.train planner.no_such_key=1
python -m mbrl_delan.train -m model=delan,no_such_model seed=0,1
python -m mbrl_delan.train seed=0,1
python -m mbrl_delan.train planner.discount=2.0
python -m mbrl_delan.train model.integrator=leapfrog
python -m mbrl_delan.train device=tpu
python -m mbrl_delan.train -m hydra/launcher=no_such_launcher seed=0,1
python -m mbrl_delan.train hydra.run.no_such_key=runs/x
python -m mbrl_delan.fit data.filter.cutoffhz=3
python -m mbrl_delan.fit model=delan model.activation=relu
python -m mbrl_delan.bench suite=no_such_suite
python -m mbrl_delan.bench --no-such-flag
python -m mbrl_delan.report runs --no-such-flag
python -m mbrl_delan.fit_report --table
python -m mbrl_delan.evaluate runs colour=red
python -m mbrl_delan.no_such_entry_point runs
```
"""


def test_made_up_commands_are_rejected() -> None:
    commands = extract_commands(Path("bogus.md"), BOGUS)
    assert len(commands) == 17
    for command in commands:
        with pytest.raises(DocCommandError) as err:
            check_command(command)
        assert f"bogus.md:{command.line}: {command.text}" in str(err.value)


SHELL = """
```bash
SHORT="budget.iterations=1 logger=none"   # a variable, used below
python -m mbrl_delan.train -m env=pendulum,cartpole \\
    model=delan seed=0 $SHORT             # a comment
pip install -e ".[dev]" && python -m mbrl_delan.report runs/<date>/<run> ... --figure x.png
export N=2; python -m mbrl_delan.bench quick=true threads=${N} > bench.log
sbatch --wrap "python -m mbrl_delan.fit model=mlp"
```

Inline, wrapped: `python -m mbrl_delan.train
model=ensemble`.
"""


def test_extraction_handles_shell_syntax() -> None:
    found = [(c.line, c.module, c.args) for c in extract_commands(Path("shell.md"), SHELL)]
    assert found == [
        (4, "mbrl_delan.train", ("-m", "env=pendulum,cartpole", "model=delan", "seed=0",
                                 "budget.iterations=1", "logger=none")),
        (6, "mbrl_delan.report", (f"runs/{PLACEHOLDER}/{PLACEHOLDER}", "--figure", "x.png")),
        (7, "mbrl_delan.bench", ("quick=true", "threads=2")),
        (8, "mbrl_delan.fit", ("model=mlp",)),
        (11, "mbrl_delan.train", ("model=ensemble",)),
    ]  # fmt: skip
    for command in extract_commands(Path("shell.md"), SHELL):
        check_command(command)


# ------------------------------------------------------------------------ config keys


def _leaf_keys(node: Any, prefix: str = "") -> Iterator[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaf_keys(value, f"{prefix}{key}.")
    else:
        yield prefix.rstrip(".")


def _sections(markdown: str) -> dict[tuple[str, str], str]:
    """(level-2 heading, level-3 heading) -> that section's text ('' for a level-2 intro)."""
    sections: dict[tuple[str, str], str] = {}
    h2 = h3 = ""
    for line in markdown.splitlines():
        if line.startswith("## "):
            h2, h3 = line[3:], ""
        elif line.startswith("### "):
            h3 = line[4:]
        sections[(h2, h3)] = sections.get((h2, h3), "") + line + "\n"
    return sections


# config files -> (level-2 heading contains, level-3 heading starts with) in configuration.md
CONFIG_SECTIONS = {
    "train/config.yaml": ("mbrl_delan.train", "Top level"),
    "train/env/*.yaml": ("mbrl_delan.train", "`env=`"),
    "train/model/*.yaml": ("mbrl_delan.train", "`model=`"),
    "train/planner/*.yaml": ("mbrl_delan.train", "`planner=`"),
    "train/logger/*.yaml": ("mbrl_delan.train", "`logger=`"),
    "train/plan/*.yaml": ("mbrl_delan.train", "`plan=`"),
    "train/tuning/*.yaml": ("mbrl_delan.train", "`tuning/`"),
    "train/plan_tuning/*.yaml": ("mbrl_delan.train", "`tuning/`"),
    "fit/config.yaml": ("mbrl_delan.fit", "Top level"),
    "fit/data/*.yaml": ("mbrl_delan.fit", "`data=`"),
    "fit/model/*.yaml": ("mbrl_delan.fit", "`model=`"),
    "fit/logger/*.yaml": ("mbrl_delan.fit", "`logger=`"),
    "bench/config.yaml": ("mbrl_delan.bench", "Top level"),
    "bench/suite/*.yaml": ("mbrl_delan.bench", "`suite=`"),
    "launchers/hydra/launcher/*.yaml": ("Hydra settings", "`hydra/launcher=`"),
}


def test_every_config_key_is_documented() -> None:
    sections = _sections((DOCS / "configuration.md").read_text(encoding="utf-8"))
    covered = {p for pattern in CONFIG_SECTIONS for p in CONFIGS.glob(pattern)}
    assert covered == set(CONFIGS.rglob("*.yaml")), "a config file has no docs section"
    missing = []
    for pattern, (h2_part, h3_start) in CONFIG_SECTIONS.items():
        text = "".join(
            body for (h2, h3), body in sections.items() if h2_part in h2 and h3.startswith(h3_start)
        )
        assert text, f"configuration.md has no section for mbrl_delan/configs/{pattern}"
        for path in sorted(CONFIGS.glob(pattern)):
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
            data = {k: v for k, v in data.items() if k not in ("defaults", "hydra")}
            for key in _leaf_keys(data):
                name = key.rsplit(".", 1)[-1]
                if not re.search(rf"`[^`\n]*\b{re.escape(name)}\b[^`\n]*`", text):
                    missing.append(f"mbrl_delan/configs/{path.relative_to(CONFIGS)}: {key}")
    assert not missing, "keys not in docs/configuration.md:\n" + "\n".join(missing)


# ------------------------------------------------------------------------ the site


def _nav_pages(node: Any) -> Iterator[str]:
    if isinstance(node, str):
        yield node
    elif isinstance(node, list):
        for item in node:
            yield from _nav_pages(item)
    elif isinstance(node, dict):
        for value in node.values():
            yield from _nav_pages(value)


def test_every_docs_page_is_in_the_nav() -> None:
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text(encoding="utf-8"))
    assert config["docs_dir"] == "docs"
    nav = list(_nav_pages(config["nav"]))
    pages = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md"))
    assert sorted(set(nav) - set(pages)) == [], "nav entries without a page"
    assert sorted(set(pages) - set(nav)) == [], "pages missing from the nav in mkdocs.yml"
    assert len(nav) == len(set(nav)), "a page is in the nav twice"


def test_mkdocs_build_strict(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs", reason="mkdocs is not installed (pip install -e '.[dev]')")
    pytest.importorskip("mkdocstrings", reason="mkdocstrings is not installed")
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr


def test_no_page_mentions_a_session() -> None:
    """The docs describe the code as it is: no development history by session."""
    hits = [
        f"{page.relative_to(REPO)}:{i}"
        for page in DOC_FILES
        for i, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1)
        if re.search(r"\bsessions?\b", line, flags=re.IGNORECASE)
    ]
    assert not hits, hits


def _section_of(lines: list[str], i: int) -> str:
    """The text of the section (from its heading to the next) holding line i."""
    start = max((j for j in range(i + 1) if lines[j].startswith("#")), default=0)
    end = next((j for j in range(i + 1, len(lines)) if lines[j].startswith("#")), len(lines))
    return "\n".join(lines[start:end])


def test_every_figure_is_shown_beside_the_command_that_makes_it() -> None:
    """Every image and video under docs/ appears on a page, and each section that shows it
    holds a `python -m mbrl_delan...` command (the one that produced it)."""
    media = sorted(p for p in DOCS.rglob("*") if p.suffix in (".png", ".svg", ".gif", ".mp4"))
    unused, without_command = [], []
    for item in media:
        shown = False
        for page in DOC_FILES:
            lines = page.read_text(encoding="utf-8").splitlines()
            for i, line in enumerate(lines):
                if f"{item.parent.name}/{item.name}" in line:
                    shown = True
                    if f"python -m {PACKAGE}" not in _section_of(lines, i):
                        without_command.append(f"{page.relative_to(REPO)}:{i + 1}")
        if not shown:
            unused.append(str(item.relative_to(REPO)))
    assert not unused, f"figures no page shows: {unused}"
    assert not without_command, f"figures without their command: {without_command}"


def test_check_site_fails_on_wide_tables_and_wrapped_code() -> None:
    """tools/check_site.py's layout rules on what a browser laid out: a table wider than the
    column and a code block shown on more lines than it has are problems; fitting ones not."""
    spec = importlib.util.spec_from_file_location("check_site", REPO / "tools" / "check_site.py")
    check_site = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check_site)
    seen = {
        "tables": [
            {"head": "arm\tfriction", "width": 900, "column": 688},
            {"head": "env\tmodel", "width": 688, "column": 688},
        ],
        "blocks": [
            {"first": "MuJoCo system --> real env", "lines": 4, "shown": 8},
            {"first": "python -m mbrl_delan.train", "lines": 1, "shown": 1},
        ],
    }
    problems = check_site.layout_problems("architecture", seen)
    assert problems == [
        "architecture: table 'arm\tfriction' is 900 px wide, the column 688 px",
        "architecture: code block 'MuJoCo system --> real env' wraps (4 lines shown as 8)",
    ]


def _where_it_stands(text: str) -> str:
    start = text.index("## Where it stands")
    return text[start : text.index("\n## ", start + 1)]


def test_the_readme_says_where_it_stands_as_the_docs_index_does() -> None:
    """README.md's "Where it stands" is docs/index.md's, word for word, its links led into
    docs/: a figure changed in one and not the other fails here."""
    index = _where_it_stands((DOCS / "index.md").read_text(encoding="utf-8"))
    readme = _where_it_stands((REPO / "README.md").read_text(encoding="utf-8"))
    expected = re.sub(r"\]\((?!https?:|#)([^)]+)\)", r"](docs/\1)", index)
    assert readme == expected, "copy docs/index.md's 'Where it stands' into README.md"
