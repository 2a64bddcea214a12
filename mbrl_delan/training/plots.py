"""Plots of a run from its ``metrics.jsonl`` (matplotlib's Agg canvas, no pyplot state)."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import yaml

from mbrl_delan.figure_style import legend_below, page_figure, save_figure
from mbrl_delan.training.recorder import METRICS_FILE, RUN_CONFIG, read_metrics

log = logging.getLogger(__name__)

ENV_STEPS = "env_steps"
EVAL_RETURN_MEAN = "eval_return_mean"
EVAL_RETURN_STD = "eval_return_std"
ORACLE_RETURN_MEAN = "oracle_return_mean"
TRAIN_RETURN = "train_return"
MODEL_ERROR_1STEP = "model_error_1step"
MODEL_ERROR_HSTEP = "model_error_hstep"

RETURNS_PNG = "returns.png"
MODEL_ERROR_PNG = "model_error.png"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _series(
    records: list[dict[str, Any]], key: str, positive: bool = False
) -> tuple[list[float], list[float]]:
    """(env_steps, value) of the records that have both, sorted by env steps."""
    pairs = sorted(
        (r[ENV_STEPS], r[key])
        for r in records
        if _is_number(r.get(ENV_STEPS)) and _is_number(r.get(key)) and (not positive or r[key] > 0)
    )
    return [p[0] for p in pairs], [p[1] for p in pairs]


def _band(records: list[dict[str, Any]]) -> tuple[list[float], list[float], list[float]]:
    """(env_steps, mean - std, mean + std) where both eval mean and std are present."""
    rows = sorted(
        (r[ENV_STEPS], r[EVAL_RETURN_MEAN], r[EVAL_RETURN_STD])
        for r in records
        if all(_is_number(r.get(k)) for k in (ENV_STEPS, EVAL_RETURN_MEAN, EVAL_RETURN_STD))
    )
    return [x for x, _, _ in rows], [m - s for _, m, s in rows], [m + s for _, m, s in rows]


def run_title(run_dir: Path) -> str:
    """``env / model / planner, seed s`` from the run's ``config.yaml`` ("" without one)."""
    try:
        cfg = yaml.safe_load((run_dir / RUN_CONFIG).read_text(encoding="utf-8"))
        parts = (cfg["env"]["name"], cfg["model"]["name"], cfg["planner"]["name"])
        return f"{' / '.join(map(str, parts))}, seed {cfg['seed']}"
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        return ""


def _plot_returns(records: list[dict[str, Any]], path: Path, title: str) -> Path | None:
    eval_x, eval_y = _series(records, EVAL_RETURN_MEAN)
    train_x, train_y = _series(records, TRAIN_RETURN)
    oracle = [r[ORACLE_RETURN_MEAN] for r in records if _is_number(r.get(ORACLE_RETURN_MEAN))]
    if not eval_x and not train_x:
        return None
    fig, axes = page_figure(4.2)
    ax = axes[0, 0]
    if eval_x:
        ax.plot(eval_x, eval_y, marker="o", label="evaluation return")
        band_x, low, high = _band(records)
        if band_x:
            ax.fill_between(band_x, low, high, alpha=0.25, label="± std")
    if train_x:
        ax.plot(train_x, train_y, alpha=0.6, linestyle="--", label="on-policy episode return")
    if oracle:
        ax.axhline(oracle[-1], color="black", linestyle=":", label="oracle return")
    ax.set(xlabel="env steps", ylabel="return", title=f"Returns: {title}" if title else "Returns")
    legend_below(fig)
    return save_figure(fig, path)


def _plot_model_error(records: list[dict[str, Any]], path: Path, title: str) -> Path | None:
    curves = {
        "one-step error": _series(records, MODEL_ERROR_1STEP, positive=True),
        "multi-step error": _series(records, MODEL_ERROR_HSTEP, positive=True),
    }
    curves = {name: xy for name, xy in curves.items() if xy[0]}
    if not curves:
        return None
    fig, axes = page_figure(4.0)
    ax = axes[0, 0]
    for name, (x, y) in curves.items():
        ax.plot(x, y, marker="o", label=name)
    ax.set_yscale("log")
    name = f"Model error: {title}" if title else "Model error"
    ax.set(xlabel="env steps", ylabel="normalised RMS error", title=name)
    legend_below(fig)
    return save_figure(fig, path)


def plot_run(run_dir: Path) -> list[Path]:
    """Write ``returns.png`` and ``model_error.png`` into ``run_dir`` from its metrics.

    A plot whose metrics are absent is skipped. Returns the paths written.
    """
    run_dir = Path(run_dir)
    records = read_metrics(run_dir / METRICS_FILE)
    if not records:
        log.warning("no metrics in %s: nothing to plot", run_dir / METRICS_FILE)
        return []
    title = run_title(run_dir)
    written = [
        _plot_returns(records, run_dir / RETURNS_PNG, title),
        _plot_model_error(records, run_dir / MODEL_ERROR_PNG, title),
    ]
    return [p for p in written if p is not None]
