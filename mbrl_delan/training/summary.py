"""A training run's ``summary.json`` from its loop and its metrics (docs/metrics.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from mbrl_delan.training.loop import MBRLLoop
from mbrl_delan.training.recorder import METRICS_FILE, read_metrics

# a paired final evaluation's figures (`MBRLLoop.paired_figures`), in the summary too
PAIRED_KEYS = ("paired_episodes", "falls", "oracle_falls", "both_stood", "standing_return_ratio")
# the last evaluation's planning time (`Evaluation.planning_figures`)
PLANNING_KEYS = ("plan_ms_median", "plan_ms_per_control_step", "plan_load_1min")
# the figures of how long a run took, which two processes of one seeded run do not share
TIMING_KEYS = ("wall_time_s", *PLANNING_KEYS, *(f"oracle_{key}" for key in PLANNING_KEYS))


def run_summary(cfg: DictConfig, run_dir: Path, loop: MBRLLoop) -> dict[str, Any]:
    """The run's names, counters, its last evaluation against the oracle's and the
    zero-control baseline, and a paired evaluation's figures."""
    last = last_evaluation(run_dir)
    oracle = loop.oracle_returns or []
    oracle_mean = loop.oracle_mean
    eval_mean = last.get("eval_return_mean", float("nan"))
    summary = {
        "env": cfg.env.name,
        "model": cfg.model.name,
        "planner": cfg.planner.name,
        "seed": cfg.seed,
        "device": cfg.device,
        "env_steps": loop.counters.env_steps,
        "episodes": loop.counters.episodes,
        "iterations": loop.counters.iteration,
        "wall_time_s": loop.counters.wall_time_s,
        "eval_return_mean": eval_mean,
        "eval_return_std": last.get("eval_return_std"),
        "oracle_return_mean": oracle_mean,
        "oracle_return_std": float(torch.tensor(oracle).std(unbiased=False)) if oracle else None,
        "fraction_of_oracle": eval_mean / oracle_mean if oracle_mean else None,
        "eval_steps_median": last.get("eval_steps_median"),
        # where the oracle's episodes come from: this run, or the run (or record) named
        "oracle_source": cfg.budget.get("oracle_from") or "this run",
    }
    figures = {k: last[k] for k in (*PAIRED_KEYS, *PLANNING_KEYS) if k in last}
    return with_zero_baseline(loop, summary | figures | loop.oracle_planning)


def last_evaluation(run_dir: Path) -> dict[str, Any]:
    """The run's last record with evaluation figures ({} before its first)."""
    records = [r for r in read_metrics(run_dir / METRICS_FILE) if "eval_return_mean" in r]
    return records[-1] if records else {}


def with_zero_baseline(loop: MBRLLoop, summary: dict[str, Any]) -> dict[str, Any]:
    """The summary with the zero-control baseline: `zero_torque_return_mean` R0 and
    `gap_closed` = (R - R0) / (R_oracle - R0) (None where undefined)."""
    zero = loop.zero_returns
    r0 = sum(zero) / len(zero) if zero else None
    gap = summary["oracle_return_mean"] - r0 if r0 is not None else None
    closed = (summary["eval_return_mean"] - r0) / gap if gap else None
    return summary | {"zero_torque_return_mean": r0, "gap_closed": closed}
