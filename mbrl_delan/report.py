"""`python -m mbrl_delan.report DIR [DIR ...] [--out DIR]`: a sweep's results over seeds.

Finds the training run dirs below the given folders (a sweep dir, ``runs/multirun``, single
run dirs), groups the finished runs (those with a ``summary.json``) by (env, model, planner,
start: ``scratch``, or the fit a DeLaN started from with ``model.init_from``; config: every
other value of ``config.yaml`` that differs between the group's runs, such as two budgets,
apart from the seed and how a run ran, `RAN_WITH`) and writes into ``--out`` (default: the
first DIR; ``<DIR>/report`` when DIR is itself a run):

* ``report.md`` and ``report.csv``: per group the seeds, n (the seeds: repeated runs of one
  seed count once, with their mean, and a warning names them), mean and 95% confidence
  interval (Student t over seeds) of the final evaluation return and of the fraction of the
  oracle, the oracle return, the env steps to reach 50%, 80% and 90% of the oracle and the
  wall time;
* ``returns.png``: one panel per env: the evaluation and on-policy returns vs env steps per
  model x planner, mean with a 95% CI band, the oracle as a dashed line;
* ``model_error.png``: the one-step and H-step model errors vs env steps, same layout.

Runs without a readable ``summary.json`` are listed in ``report.md`` and on the log, with the
message of their ``crash.json`` when there is one; they never stop the report.
See ``docs/sweeps.md`` for the formulas.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import os
import statistics
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mbrl_delan.conf.checks import migrate
from mbrl_delan.figure_style import legend_below, page_figure, save_figure
from mbrl_delan.intervals import CONFIDENCE, mcnemar_exact, mean_ci, wilson_interval
from mbrl_delan.provenance import program_name
from mbrl_delan.stops import stop_line
from mbrl_delan.sweep import CRASH_FILE, last_iteration, read_crash
from mbrl_delan.training.recorder import METRICS_FILE, RUN_CONFIG, flat_config, read_metrics

log = logging.getLogger(__name__)

SUMMARY = "summary.json"
RUN_FILES = (RUN_CONFIG, SUMMARY, CRASH_FILE)
GROUP_KEYS = ("env", "model", "planner", "start", "config")
# config keys (and prefixes, ending in "."): how a run ran, not what it measured; runs that
# differ only in these (and the seed) are seeds of one group
RAN_WITH = (
    "seed", "device", "threads", "resume", "logger.", "video", "video_width", "video_height",
    "video_episodes", "video_every_eval", "video_backend", "buffer.memmap", "buffer.device",
    "buffer.device_fraction", "budget.oracle_from", "accel.",
)  # fmt: skip
REQUIRED_KEYS = ("env", "model", "planner", "seed")
ORACLE_FRACTION = 0.9
REACH_FRACTIONS = (0.5, 0.8, ORACLE_FRACTION)  # the table's "env steps to x of the oracle"
SCRATCH = "scratch"  # a run's start when its model did not start from a fit

REPORT_MD = "report.md"
REPORT_CSV = "report.csv"
RETURNS_PNG = "returns.png"
MODEL_ERROR_PNG = "model_error.png"

# a paired final evaluation's falls, pooled over the seeds' episodes (`paired_falls`)
FALL_COLUMNS = (
    "paired_episodes", "falls", "falls_ci95_low", "falls_ci95_high", "oracle_falls",
    "oracle_falls_ci95_low", "oracle_falls_ci95_high", "model_fell_only", "oracle_fell_only",
    "mcnemar_p",
)  # fmt: skip
COLUMNS = (
    *GROUP_KEYS,
    "seeds",
    "n",
    "eval_return_mean",
    "eval_return_ci95",
    "fraction_of_oracle_mean",
    "fraction_of_oracle_ci95",
    "oracle_return_mean",
    "oracle_return_ci95",
    *(f"steps_to_{100 * f:.0f}_{part}" for f in REACH_FRACTIONS for part in ("mean", "reached")),
    "env_steps_mean",
    "wall_time_s_mean",
    *FALL_COLUMNS,
)

Group = tuple[str, str, str, str, str]


# --- finding runs -------------------------------------------------------------------------


def _is_train_config(path: Path) -> bool:
    """Whether a saved Hydra config is one of ``mbrl_delan.train`` (it has planner and budget)."""
    try:
        cfg = OmegaConf.load(path)
    except (OSError, ValueError, yaml.YAMLError) as err:
        log.warning("unreadable %s: %s", path, err)
        return False
    return OmegaConf.is_dict(cfg) and "planner" in cfg and "budget" in cfg


def is_run_dir(path: Path) -> bool:
    """Whether ``path`` is a training run dir, finished or not.

    A dir Hydra made (``.hydra/config.yaml``) is one when that config is a training config (a
    run killed before it wrote anything is still found), or when the run's own ``config.yaml``
    is (Hydra rewrites its record at every launch in the dir, a refused one of another program
    too); any other dir is one when it holds ``config.yaml``, ``summary.json`` or ``crash.json``.
    """
    hydra_cfg = path / ".hydra" / RUN_CONFIG
    if hydra_cfg.is_file():
        own_cfg = path / RUN_CONFIG
        return _is_train_config(hydra_cfg) or (own_cfg.is_file() and _is_train_config(own_cfg))
    return any((path / name).is_file() for name in RUN_FILES)


def run_dirs(roots: Iterable[Path]) -> list[Path]:
    """Run dirs at or below the roots, sorted; run dirs are not searched for nested runs.

    Hidden folders (``.hydra``, ``.submitit``) and ``wandb`` folders are skipped; links to
    folders are followed (each real folder once).
    """
    found: set[Path] = set()
    seen: set[Path] = set()  # real paths walked: a link back up is not walked twice
    for root in roots:
        for dirpath, dirnames, _ in os.walk(root, followlinks=True):
            path = Path(dirpath)
            real = path.resolve()
            if real in seen:
                dirnames[:] = []
                continue
            seen.add(real)
            if is_run_dir(path):
                found.add(path)
                dirnames[:] = []
            else:
                dirnames[:] = [d for d in dirnames if not d.startswith(".") and d != "wandb"]
    return sorted(found)


def _load_summary(run: Path) -> dict[str, Any] | None:
    """The run's summary with ``run_dir`` added, or None when missing, unreadable or foreign."""
    try:
        summary = json.loads((run / SUMMARY).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or any(k not in summary for k in REQUIRED_KEYS):
        return None
    return {**summary, "run_dir": str(run), "start": run_start(run), "config": run_config(run)}


def run_start(run: Path) -> str:
    """How the run's model started: ``scratch``, or ``from <fit dir>`` (``model.init_from``
    in its ``config.yaml``)."""
    try:
        cfg = yaml.safe_load((run / RUN_CONFIG).read_text(encoding="utf-8"))
        source = cfg["model"].get("init_from")
    except (OSError, KeyError, TypeError, AttributeError, yaml.YAMLError):
        source = None
    return f"from {Path(source).name}" if source else SCRATCH


def run_config(run: Path) -> dict[str, Any]:
    """The run's ``config.yaml`` as ``{"a.b": value}`` (`flat_config`), in today's keys
    (`migrate`: a run saved before a key was added, moved or removed groups with today's runs
    of the same settings); {} when it is missing or unreadable."""
    try:
        cfg = yaml.safe_load((run / RUN_CONFIG).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return {}
    if not isinstance(cfg, dict):
        return {}
    try:
        current = OmegaConf.to_container(migrate(OmegaConf.create(cfg)))
    except OmegaConfBaseException:  # not a train config: its keys as saved
        current = cfg
    return flat_config(current)


def _ran_with(key: str) -> bool:
    return any(key.startswith(k) if k.endswith(".") else key == k for k in RAN_WITH)


def differing_keys(configs: list[dict[str, Any]]) -> list[str]:
    """The config keys whose values differ between ``configs``, apart from `RAN_WITH`."""
    keys = sorted({k for c in configs for k in c})
    return [k for k in keys if not _ran_with(k) and len({c.get(k) for c in configs}) > 1]


def find_runs(roots: list[Path]) -> tuple[list[dict[str, Any]], list[Path]]:
    """Summaries of finished runs, and the run dirs without a usable ``summary.json``."""
    summaries, incomplete = [], []
    for run in run_dirs(roots):
        read_metrics(run / METRICS_FILE)  # its damaged lines named once; later reads are quiet
        summary = _load_summary(run)
        if summary is None:
            incomplete.append(run)
            continue
        summaries.append(summary)
        if (run / CRASH_FILE).is_file():
            log.warning("%s has %s and %s: it crashed after its summary", run, SUMMARY, CRASH_FILE)
    return summaries, incomplete


def incomplete_reason(run: Path) -> str:
    """Why a run has no usable summary, e.g. ``crashed: ValueError: bad (after iteration 2)``."""
    crash = read_crash(run)
    done = last_iteration(run, warn=False)
    after = f" (after iteration {done})" if done is not None else ""
    if crash is not None:
        return f"crashed: {crash.get('type', '?')}: {crash.get('message', '')}{after}"
    if (run / SUMMARY).is_file():
        return f"{SUMMARY} unreadable or without {', '.join(REQUIRED_KEYS)}"
    return f"no {SUMMARY}: still running, killed or timed out{after}"


# --- statistics ---------------------------------------------------------------------------


def _finite(values: Iterable[Any]) -> list[float]:
    out = []
    for v in values:
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
            out.append(float(v))
    return out


def paired_falls(run: dict[str, Any]) -> tuple[list[bool], list[bool]] | None:
    """Per episode of a run's paired final evaluation: whether the model fell and whether
    the oracle fell from the same start (an episode shorter than ``env.episode_len``); None
    without one."""
    records = read_metrics(Path(run["run_dir"]) / METRICS_FILE, warn=False)
    last = next((r for r in reversed(records) if "oracle_episode_steps" in r), None)
    if last is None or "eval_episode_steps" not in last:
        return None
    ours, theirs = last["eval_episode_steps"], last["oracle_episode_steps"]
    n = min(len(ours), len(theirs))
    full = run["config"].get("env.episode_len") or max(ours[:n] + theirs[:n], default=0)
    return [s < full for s in ours[:n]], [s < full for s in theirs[:n]]


def fall_figures(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """`FALL_COLUMNS` over the paired episodes of `runs` (every seed's, pooled): the falls
    of the model and of the oracle with their Wilson intervals, the discordant episodes and
    the exact McNemar p-value; None each without paired episodes."""
    pairs = [p for r in runs if (p := paired_falls(r)) is not None]
    model = [f for ours, _ in pairs for f in ours]
    oracle = [f for _, theirs in pairs for f in theirs]
    if not model:
        return dict.fromkeys(FALL_COLUMNS)
    b = sum(m and not o for m, o in zip(model, oracle, strict=True))
    c = sum(o and not m for m, o in zip(model, oracle, strict=True))
    n, falls, oracle_falls = len(model), sum(model), sum(oracle)
    low, high = wilson_interval(falls, n)
    oracle_low, oracle_high = wilson_interval(oracle_falls, n)
    return {
        "paired_episodes": n, "falls": falls, "falls_ci95_low": low, "falls_ci95_high": high,
        "oracle_falls": oracle_falls, "oracle_falls_ci95_low": oracle_low,
        "oracle_falls_ci95_high": oracle_high, "model_fell_only": b, "oracle_fell_only": c,
        "mcnemar_p": mcnemar_exact(b, c),
    }  # fmt: skip


def steps_to_fraction(
    records: list[dict[str, Any]], oracle: float | None, fraction: float = ORACLE_FRACTION
) -> int | None:
    """Env steps at the first evaluation with return >= oracle - (1 - fraction) * |oracle|.

    (That is ``fraction`` x oracle for a positive oracle.) Records in logged order; None when no
    evaluation reaches it or the oracle is unknown.
    """
    if not _finite([oracle]):
        return None
    threshold = oracle - (1.0 - fraction) * abs(oracle)
    for rec in records:
        ret, steps = rec.get("eval_return_mean"), rec.get("env_steps")
        if _finite([ret]) and _finite([steps]) and ret >= threshold:
            return int(steps)
    return None


def _groups(summaries: list[dict[str, Any]]) -> dict[Group, list[dict[str, Any]]]:
    """Runs by (env, model, planner, start), split by the config values that differ between
    them (``config``: ``key=value`` pairs, empty when none do; a key a run's config lacks,
    one added after it ran, is left out of its pairs). The model by its current name."""
    by_kind: dict[tuple[str, ...], list[dict[str, Any]]] = defaultdict(list)
    for s in summaries:
        model = s.get("config", {}).get("model.name", s["model"])
        by_kind[(str(s["env"]), str(model), str(s["planner"]), str(s["start"]))].append(s)
    groups: dict[Group, list[dict[str, Any]]] = defaultdict(list)
    for kind, runs in by_kind.items():
        keys = differing_keys([r.get("config", {}) for r in runs])
        for r in runs:
            values = {k: r.get("config", {}).get(k) for k in keys}
            config = " ".join(f"{k}={v}" for k, v in values.items() if v is not None)
            groups[(*kind, config)].append(r)  # type: ignore[arg-type]
    return {k: sorted(v, key=lambda s: s["seed"]) for k, v in sorted(groups.items())}


def _by_seed(runs: list[dict[str, Any]]) -> dict[Any, list[dict[str, Any]]]:
    """A group's runs by seed (repeated runs of one seed count once: the seeds, not the
    runs, are the samples)."""
    by_seed: dict[Any, list[dict[str, Any]]] = defaultdict(list)
    for r in runs:
        by_seed[r["seed"]].append(r)
    return dict(by_seed)


def _seed_means(by_seed: dict[Any, list[dict[str, Any]]], key: str) -> list[float]:
    """One value per seed: the mean of its runs' finite values of `key` (seeds with none
    are left out)."""
    means = [_finite(r.get(key) for r in rs) for rs in by_seed.values()]
    return [statistics.fmean(v) for v in means if v]


def _row(group: Group, runs: list[dict[str, Any]]) -> dict[str, Any]:
    by_seed = _by_seed(runs)
    repeated = {seed: len(rs) for seed, rs in by_seed.items() if len(rs) > 1}
    if repeated:
        log.warning(
            "%s: seeds repeat (%s): each seed counts once, with the mean of its runs",
            group, ", ".join(f"seed {seed} x{k}" for seed, k in repeated.items()),
        )  # fmt: skip
    row: dict[str, Any] = dict(zip(GROUP_KEYS, group, strict=True))
    row.update(seeds=" ".join(map(str, by_seed)), n=len(by_seed))
    for key, name in (
        ("eval_return_mean", "eval_return"),
        ("fraction_of_oracle", "fraction_of_oracle"),
        ("oracle_return_mean", "oracle_return"),
    ):
        row[f"{name}_mean"], row[f"{name}_ci95"] = mean_ci(_seed_means(by_seed, key))
    for fraction in REACH_FRACTIONS:
        reached = []  # per seed, the mean over its runs that reached the fraction
        for seed_runs in by_seed.values():
            steps = [
                steps_to_fraction(
                    read_metrics(Path(r["run_dir"]) / METRICS_FILE, warn=False),
                    r.get("oracle_return_mean"),
                    fraction,
                )
                for r in seed_runs
            ]
            steps = [x for x in steps if x is not None]
            if steps:
                reached.append(statistics.fmean(steps))
        name = f"steps_to_{100 * fraction:.0f}"
        row[f"{name}_mean"] = statistics.fmean(reached) if reached else None
        row[f"{name}_reached"] = len(reached)
    row["env_steps_mean"] = mean_ci(_seed_means(by_seed, "env_steps"))[0]
    row["wall_time_s_mean"] = mean_ci(_seed_means(by_seed, "wall_time_s"))[0]
    return row | fall_figures([rs[0] for rs in by_seed.values()])


def rows(summaries: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One dict per (env, model, planner, start, config) with the keys of ``COLUMNS``; None
    where n/a."""
    return [_row(group, runs) for group, runs in _groups(summaries).items()]


# --- tables -------------------------------------------------------------------------------


def _pm(mean: float | None, half: float | None) -> str:
    if mean is None:
        return "n/a"
    return f"{mean:.3g} ± {'n/a' if half is None else format(half, '.2g')}"


def _plain(value: float | None, spec: str = ".3g") -> str:
    return "n/a" if value is None else format(value, spec)


def table(summaries: list[dict[str, Any]]) -> str:
    """Markdown: one row per (env, model, planner, start, config), mean ± 95% CI half-width
    over seeds."""
    return markdown_table(rows(summaries))


def markdown_table(table_rows: list[dict[str, Any]]) -> str:
    """The Markdown table of ``rows``' output."""
    lines = [
        "| env | model | planner | start | config | seeds | n | eval return | fraction of oracle "
        "| oracle return | env steps to 50% / 80% / 90% of oracle (seeds reaching) "
        "| env steps | wall time (s) | falls / paired episodes (95% CI) | oracle's falls (95% CI) "
        "| McNemar p (model fell only / oracle fell only) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table_rows:
        cells = [
            r["env"],
            r["model"],
            r["planner"],
            r["start"],
            f"`{r['config']}`" if r["config"] else "",
            r["seeds"].replace(" ", ","),
            str(r["n"]),
            _pm(r["eval_return_mean"], r["eval_return_ci95"]),
            _pm(r["fraction_of_oracle_mean"], r["fraction_of_oracle_ci95"]),
            _pm(r["oracle_return_mean"], r["oracle_return_ci95"]),
            " / ".join(_reach(r, fraction) for fraction in REACH_FRACTIONS),
            _plain(r["env_steps_mean"], ".0f"),
            _plain(r["wall_time_s_mean"], ".0f"),
            *_fall_cells(r),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _fall_cells(r: dict[str, Any]) -> list[str]:
    """The falls, the oracle's and the paired test, as the table shows them (n/a unpaired)."""
    n = r["paired_episodes"]
    if not n:
        return ["n/a"] * 3
    return [
        f"{r['falls']}/{n} ({r['falls_ci95_low']:.0%}-{r['falls_ci95_high']:.0%})",
        f"{r['oracle_falls']}/{n} ({r['oracle_falls_ci95_low']:.0%}-"
        f"{r['oracle_falls_ci95_high']:.0%})",
        f"{r['mcnemar_p']:.2g} ({r['model_fell_only']} / {r['oracle_fell_only']})",
    ]


def falls_table(table_rows: list[dict[str, Any]]) -> str:
    """Markdown: the groups with paired final episodes, their falls against the oracle's
    (pooled over seeds, Wilson 95% intervals), the exact McNemar p and the fraction of the
    oracle's return: the narrow table `--page` writes into a docs page."""
    lines = [
        "| env | model | config | seeds | falls / paired (95% CI) | oracle's falls (95% CI) "
        "| McNemar p (model only / oracle only) | fraction of oracle |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in table_rows:
        if r["paired_episodes"]:
            config = f"`{r['config']}`" if r["config"] else ""
            seeds = r["seeds"].replace(" ", ",")
            fraction = _pm(r["fraction_of_oracle_mean"], r["fraction_of_oracle_ci95"])
            cells = [r["env"], _model_cell(r), config, seeds, *_fall_cells(r), fraction]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _model_cell(row: dict[str, Any]) -> str:
    """The model, and where it started when not from scratch (a fit, `model.init_from`)."""
    return row["model"] if row["start"] == SCRATCH else f"{row['model']} ({row['start']})"


def returns_table(table_rows: list[dict[str, Any]]) -> str:
    """Markdown: per group the seeds, the fraction of the oracle's return and the final
    evaluation return (mean ± the 95% interval's half-width over seeds) and the env steps:
    the narrow table `--page` writes for runs without paired episodes."""
    lines = [
        "| env | model | planner | config | seeds | fraction of oracle | eval return | env steps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in table_rows:
        config = f"`{r['config']}`" if r["config"] else ""
        cells = [r["env"], _model_cell(r), r["planner"], config, r["seeds"].replace(" ", ","),
                 _pm(r["fraction_of_oracle_mean"], r["fraction_of_oracle_ci95"]),
                 _pm(r["eval_return_mean"], r["eval_return_ci95"]),
                 _plain(r["env_steps_mean"], ".0f")]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


PAGE_BEGIN, PAGE_END = "<!-- report:begin -->", "<!-- report:end -->"


def page_tables(summaries: list[dict[str, Any]]) -> str:
    """`falls_table` of the runs with paired final episodes and `returns_table` of the
    others, each set grouped among itself (the tables present)."""
    is_paired = [paired_falls(s) is not None for s in summaries]
    paired = [s for s, p in zip(summaries, is_paired, strict=True) if p]
    others = [s for s, p in zip(summaries, is_paired, strict=True) if not p]
    tables = []
    if paired:
        tables.append(falls_table(rows(paired)))
    if others:
        tables.append(returns_table(rows(others)))
    return "\n\n".join(tables)


def write_page(page: Path, command: str, summaries: list[dict[str, Any]]) -> Path:
    """Replace what lies between `PAGE_BEGIN` and `PAGE_END` in `page` by the command and
    its `page_tables`. Raises ValueError when the page lacks the markers (nothing written)."""
    text = page.read_text(encoding="utf-8")
    begin, end = text.find(PAGE_BEGIN), text.find(PAGE_END)
    if begin < 0 or end < begin:
        raise ValueError(f"{page} has no {PAGE_BEGIN} ... {PAGE_END} block to write into")
    block = f"{PAGE_BEGIN}\n```bash\n{command}\n```\n\n{page_tables(summaries)}\n"
    page.write_text(text[:begin] + block + text[end:], encoding="utf-8")
    return page


def _reach(row: dict[str, Any], fraction: float) -> str:
    name = f"steps_to_{100 * fraction:.0f}"
    return f"{_plain(row[f'{name}_mean'], '.0f')} ({row[f'{name}_reached']}/{row['n']})"


def write_csv(table_rows: list[dict[str, Any]], path: Path) -> Path:
    """``COLUMNS`` as a header, one line per group; full precision, empty cells for n/a."""
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        for r in table_rows:
            writer.writerow({k: "" if r[k] is None else r[k] for k in COLUMNS})
    return path


def markdown(table_rows: list[dict[str, Any]], incomplete: list[Path], figures: list[Path]) -> str:
    """The whole ``report.md``: the table, the incomplete runs and the figures."""
    finished = sum(r["n"] for r in table_rows)
    parts = [
        "# Training runs",
        f"{finished} finished runs, {len(incomplete)} incomplete.",
        markdown_table(table_rows),
        f"Mean ± half-width of the {CONFIDENCE:.0%} confidence interval over seeds (Student t; "
        "n/a for one seed). Fraction of oracle: final evaluation return / the same planner's "
        "return on MuJoCo's dynamics, per seed. Env steps to x of oracle: first evaluation "
        "reaching it, mean over the seeds that did. Start: scratch, or the fit the model "
        "started from (`model.init_from`). Config: the settings that differ between runs of "
        "the same env, model, planner and start (none: they differ only in the seed). Falls: "
        "episodes of the paired final evaluation shorter than the env's, pooled over the "
        "seeds (the first run of each), with the Wilson 95% interval; the oracle's from the "
        "same starts and planner seeds; McNemar p: the exact two-sided test on the episodes "
        "where only one of them fell.",
        "## Incomplete runs",
        "\n".join(f"- `{run}`: {incomplete_reason(run)}" for run in incomplete) or "None.",
    ]
    if figures:
        parts += ["## Figures", " ".join(f"![{p.stem}]({p.name})" for p in figures)]
    return "\n\n".join(parts) + "\n"


# --- figures ------------------------------------------------------------------------------


def curves(summaries: list[dict[str, Any]], key: str) -> dict[Group, dict[int, list[float]]]:
    """Per group, the values of metric ``key`` by env step, one per seed. Seeds whose rounds
    end at different env steps (episodes that end early) are put on one grid, the union of
    their steps: each seed gives its value linearly interpolated at the grid's steps within
    its own first and last."""
    out: dict[Group, dict[int, list[float]]] = {}
    for group, runs in _groups(summaries).items():
        seeds = [
            [s for s in (_series(Path(r["run_dir"]) / METRICS_FILE, key) for r in rs) if s[0]]
            for rs in _by_seed(runs).values()
        ]  # per seed, its runs' series
        grid = sorted({step for series in seeds for x, _ in series for step in x})
        out[group] = {step: _at(seeds, step) for step in grid}
    return out


def _at(seeds: list[list[tuple[list[int], list[float]]]], step: int) -> list[float]:
    """One value per seed at `step`: the mean of its runs' series interpolated there (each
    within its own first and last step; seeds with none there are left out)."""
    values = []
    for series in seeds:
        inside = [float(np.interp(step, x, y)) for x, y in series if x[0] <= step <= x[-1]]
        if inside:
            values.append(statistics.fmean(inside))
    return values


def _series(metrics: Path, key: str) -> tuple[list[int], list[float]]:
    """(env steps, values) of metric ``key`` in a run's records, in logged order."""
    steps, values = [], []
    for rec in read_metrics(metrics, warn=False):
        if _finite([rec.get(key)]) and _finite([rec.get("env_steps")]):
            steps.append(int(rec["env_steps"]))
            values.append(float(rec[key]))
    return steps, values


def group_label(group: Group) -> str:
    """``model + planner``, the start when the model started from a fit, and the config
    values that set the group apart."""
    _, model, planner, start, config = group
    return (
        f"{model} + {planner}"
        + ("" if start == SCRATCH else f", {start}")
        + (f", {config}" if config else "")
    )


def _draw_band(
    ax: Any, by_step: dict[int, list[float]], color: str, label: str, style: str = "-"
) -> None:
    """Mean line and 95% CI band over seeds (no band where one seed; an error bar for a
    curve of one point) for a solid `style`, the mean alone for another; "" for no legend
    entry."""
    steps = sorted(by_step)
    stat = [mean_ci(by_step[t]) for t in steps]
    mean = [m for m, _ in stat]
    half = [h or 0.0 for _, h in stat]
    solid = style == "-"
    marker = "o" if solid else ""
    ax.plot(steps, mean, style, marker=marker, ms=3, color=color, label=label or "_nolegend_")
    if not solid:
        return
    if len(steps) == 1:  # a lone point (a final evaluation only): its interval as a bar
        ax.errorbar(steps, mean, yerr=half, fmt="none", ecolor=color, capsize=4, lw=1.2)
        return
    low = [m - h for m, h in zip(mean, half, strict=True)]
    high = [m + h for m, h in zip(mean, half, strict=True)]
    ax.fill_between(steps, low, high, color=color, alpha=0.15, lw=0)


def _colours(groups: Iterable[Group]) -> dict[str, str]:
    """One colour per group label, the same on every panel."""
    labels = sorted({group_label(g) for g in groups})
    return {label: f"C{i % 10}" for i, label in enumerate(labels)}


def _seeds(summaries: list[dict[str, Any]], env: str) -> str:
    seeds = sorted({int(s["seed"]) for s in summaries if s["env"] == env})
    return ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(map(str, seeds))


def _oracle_planner(summary: dict[str, Any]) -> str:
    """The planner of a run's oracle: iLQR (``budget.oracle_planner=ilqr`` in its
    ``config.yaml``) or the run's own planner."""
    try:
        cfg = yaml.safe_load((Path(summary["run_dir"]) / RUN_CONFIG).read_text(encoding="utf-8"))
        ilqr = cfg["budget"]["oracle_planner"] == "ilqr"
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        ilqr = False
    return "iLQR" if ilqr else str(summary["planner"])


def _oracles(summaries: list[dict[str, Any]], env: str) -> dict[str, float]:
    """Per oracle planner, the mean oracle return of the env's runs (the oracle has no model)."""
    by_planner: dict[str, list[float]] = defaultdict(list)
    for s in summaries:
        if s["env"] == env:
            by_planner[_oracle_planner(s)] += _finite([s.get("oracle_return_mean")])
    return {p: statistics.fmean(v) for p, v in sorted(by_planner.items()) if v}


# (metric, line style, what the style means in the legend), per figure
RETURN_LINES = (
    ("eval_return_mean", "-", "evaluation return"),
    ("train_return", ":", "on-policy episode return"),
)
ERROR_LINES = (
    ("model_error_1step", "-", "one-step error"),
    ("model_error_hstep", "--", "H-step error"),
)


def _panels(
    summaries: list[dict[str, Any]], lines: tuple[tuple[str, str, str], ...], title: str
) -> tuple[Any, list[str], dict[str, dict[Group, dict[int, list[float]]]]]:
    """A page-wide figure with one panel per env (task), the curves of `lines` per group,
    the style key (what each line style means) in the legend, and the figure's title."""
    by_metric = {key: curves(summaries, key) for key, _, _ in lines}
    groups = {g for c in by_metric.values() for g in c}
    envs = sorted({g[0] for g in groups}) or ["no runs"]
    fig, axes = page_figure(0.6 + 2.7 * len(envs), len(envs), 1)
    colours = _colours(groups)
    for ax, env in zip(axes[:, 0], envs, strict=True):
        for key, style, _ in lines:
            first = key == lines[0][0]  # one legend entry per group, from its first line
            for group in sorted(g for g in by_metric[key] if g[0] == env):
                label = group_label(group)
                _draw_band(ax, by_metric[key][group], colours[label], label if first else "", style)
        ax.set(title=f"{env}, {_seeds(summaries, env)}", xlabel="env steps")
    for _, style, meaning in lines:
        axes[0, 0].plot([], [], style, color="0.4", label=meaning)
    fig.suptitle(f"{title} ({spread_note(by_metric[lines[0][0]])})")
    return fig, envs, by_metric


def spread_note(curves_by_group: dict[Group, dict[int, list[float]]]) -> str:
    """What the solid curves show: a mean with its 95% CI band where two or more seeds share
    an env-step count, else single runs (a title says which, never an interval not drawn)."""
    counts = [len(values) for by_step in curves_by_group.values() for values in by_step.values()]
    if counts and min(counts) >= 2:
        return "solid: mean and 95% CI over seeds"
    if any(n >= 2 for n in counts):
        return "solid: mean; 95% CI where two or more seeds share a step"
    return "one run per point, no interval"


def returns_figure(summaries: list[dict[str, Any]], path: Path) -> Path:
    """Returns vs env steps, one panel per env: per model x planner the evaluation return
    (solid) and each round's on-policy episode return (dotted, logged every round), mean and
    95% CI band over seeds (the title says where there is none, `spread_note`); each
    planner's oracle (mean over its runs) a dashed grey line and the zero-torque return (mean
    over the runs that logged it) a dash-dotted one."""
    fig, envs, _ = _panels(summaries, RETURN_LINES, "Return vs env steps")
    for ax, env in zip(fig.axes, envs, strict=True):
        for i, (planner, oracle) in enumerate(_oracles(summaries, env).items()):
            grey = str(0.3 * (i % 3))
            ax.axhline(oracle, color=grey, ls="--", lw=1.2, label=f"oracle: {planner} on MuJoCo")
        zero = _finite([s.get("zero_torque_return_mean") for s in summaries if s["env"] == env])
        if zero:
            ax.axhline(statistics.fmean(zero), color="0.5", ls="-.", lw=1.2, label="zero torque")
        ax.set_ylabel("return")
    legend_below(fig)
    return save_figure(fig, path)


def model_error_figure(summaries: list[dict[str, Any]], path: Path) -> Path:
    """Model errors vs env steps, one panel per env: per model x planner the one-step
    (solid) and H-step (dashed) errors, mean and 95% CI band over seeds, log axis (see
    ``docs/metrics.md`` for the errors' definitions)."""
    fig, envs, by_metric = _panels(summaries, ERROR_LINES, "Model error vs env steps")
    for ax, env in zip(fig.axes, envs, strict=True):
        curves_of_env = [by for c in by_metric.values() for g, by in c.items() if g[0] == env]
        values = [v for by in curves_of_env for vs in by.values() for v in vs]
        if values and min(values) > 0:
            ax.set_yscale("log")
        ax.set_ylabel("normalised RMS error")
    legend_below(fig)
    return save_figure(fig, path)


# --- entry point --------------------------------------------------------------------------


def write_report(
    summaries: list[dict[str, Any]],
    table_rows: list[dict[str, Any]],
    incomplete: list[Path],
    out: Path,
) -> dict[str, Path]:
    """Write ``report.md``, ``report.csv`` and (with finished runs) the two figures to ``out``.

    ``table_rows`` is ``rows(summaries)``. Returns the paths written, by kind.
    """
    out.mkdir(parents=True, exist_ok=True)
    paths = {"csv": write_csv(table_rows, out / REPORT_CSV)}
    if summaries:
        paths["returns"] = returns_figure(summaries, out / RETURNS_PNG)
        paths["model_error"] = model_error_figure(summaries, out / MODEL_ERROR_PNG)
    figures = [p for k, p in paths.items() if k != "csv"]
    paths["md"] = out / REPORT_MD
    paths["md"].write_text(markdown(table_rows, incomplete, figures), encoding="utf-8")
    return paths


def _write_page(args: argparse.Namespace, summaries: list[dict[str, Any]]) -> int:
    """`--page`: the tables (`page_tables`) into the page, the command that wrote them above."""
    roots = " ".join(str(r) for r in args.roots)
    command = f"python -m mbrl_delan.report {roots} --page {args.page}"
    try:
        log.info("wrote %s", write_page(args.page, command, summaries))
    except (OSError, ValueError) as err:
        stop_line("cannot write the page", f"{err}; nothing written")
        return 2
    return 0


def default_out(root: Path) -> Path:
    """Where the report goes without ``--out``: ``root``, or ``root/report`` for a run dir."""
    return root / "report" if is_run_dir(root) else root


def figure_path(figure: Path, out: Path) -> Path:
    """Where ``--figure`` goes: a bare file name into the report's folder `out`, a path with
    a folder where it says."""
    return out / figure if figure.parent == Path(".") else figure


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog=program_name("mbrl_delan.report"), description=__doc__.splitlines()[0]
    )
    parser.add_argument("roots", nargs="+", type=Path, help="folders holding run dirs")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: DIR)")
    parser.add_argument(
        "--figure",
        type=Path,
        default=None,
        help="also write the returns figure here (a bare file name: into --out)",
    )
    parser.add_argument(
        "--page",
        type=Path,
        default=None,
        help="write only the falls and returns tables, with this command, into this Markdown "
        f"page between its {PAGE_BEGIN} and {PAGE_END} lines",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    missing = [r for r in args.roots if not r.is_dir()]
    if missing:
        stop_line("not a folder", ", ".join(map(str, missing)))
        return 2
    summaries, incomplete = find_runs(args.roots)
    if not summaries and not incomplete:
        folders = ", ".join(map(str, args.roots))
        stop_line("no runs", f"none in {folders} (a run dir holds config.yaml, summary.json or "
                  "crash.json); nothing written")  # fmt: skip
        return 2
    if args.page is not None:
        return _write_page(args, summaries)
    table_rows = rows(summaries)
    print(markdown_table(table_rows))  # the table is the output: standard output
    for run in incomplete:
        log.warning("incomplete run %s: %s", run, incomplete_reason(run))
    out = args.out or default_out(args.roots[0])
    paths = write_report(summaries, table_rows, incomplete, out)
    if args.figure is not None and summaries:
        paths["figure"] = returns_figure(summaries, figure_path(args.figure, out))
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
