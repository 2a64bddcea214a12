"""`python -m mbrl_delan.report DIR [DIR ...] [--figure PNG]`: runs' returns against the oracle.

Reads every `summary.json` below the given folders, groups runs by (env, model, planner) and
prints a Markdown table of mean and std over seeds of the final evaluation return, the
oracle return and their ratio. Run dirs without a `summary.json` are listed as incomplete.
`--figure` also draws evaluation return vs env steps per group (mean and std over seeds,
from each run's `metrics.jsonl`) with the oracle's return, one panel per env.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

SUMMARY = "summary.json"
RUN_MARKER = "config.yaml"


def find_runs(roots: list[Path]) -> tuple[list[dict[str, Any]], list[Path]]:
    """Summaries of finished runs, and run dirs that have a config but no summary."""
    summaries, incomplete = [], []
    for root in roots:
        for config in sorted(root.rglob(RUN_MARKER)):
            run = config.parent
            if run.name == ".hydra":
                continue
            path = run / SUMMARY
            if path.is_file():
                summaries.append({**json.loads(path.read_text()), "run_dir": str(run)})
            else:
                incomplete.append(run)
    return summaries, incomplete


def _mean_std(values: list[float]) -> str:
    if not values:
        return "-"
    std = statistics.pstdev(values) if len(values) > 1 else 0.0
    return f"{statistics.fmean(values):.3g} ± {std:.2g}"


def table(summaries: list[dict[str, Any]]) -> str:
    """Markdown: one row per (env, model, planner), statistics over seeds."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for s in summaries:
        groups[(s["env"], s["model"], s["planner"])].append(s)
    lines = [
        "| env | model | planner | seeds | env steps | eval return | oracle return "
        "| fraction of oracle | wall time (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (env, model, planner), runs in sorted(groups.items()):
        seeds = ",".join(str(r["seed"]) for r in sorted(runs, key=lambda r: r["seed"]))
        col = {
            k: [float(r[k]) for r in runs if r.get(k) is not None]
            for k in (
                "env_steps",
                "eval_return_mean",
                "oracle_return_mean",
                "fraction_of_oracle",
                "wall_time_s",
            )
        }
        lines.append(
            f"| {env} | {model} | {planner} | {seeds} | {_mean_std(col['env_steps'])} "
            f"| {_mean_std(col['eval_return_mean'])} | {_mean_std(col['oracle_return_mean'])} "
            f"| {_mean_std(col['fraction_of_oracle'])} | {_mean_std(col['wall_time_s'])} |"
        )
    return "\n".join(lines)


def _curves(summaries: list[dict[str, Any]]) -> dict[tuple[str, str, str], dict[int, list[float]]]:
    """Evaluation returns by env step, per group, across seeds."""
    from mbrl_delan.training.recorder import read_metrics

    curves: dict[tuple[str, str, str], dict[int, list[float]]] = defaultdict(
        lambda: defaultdict(list)
    )
    for s in summaries:
        for rec in read_metrics(Path(s["run_dir"]) / "metrics.jsonl"):
            if rec.get("eval_return_mean") is not None:
                group = curves[(s["env"], s["model"], s["planner"])]
                group[int(rec["env_steps"])].append(float(rec["eval_return_mean"]))
    return curves


def figure(summaries: list[dict[str, Any]], path: Path) -> Path:
    """Evaluation return vs env steps, one panel per env, mean +- std over seeds.

    Each group's oracle (its planner on MuJoCo's dynamics, same initial states) is a dotted
    line in the group's colour.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    curves = _curves(summaries)
    envs = sorted({k[0] for k in curves})
    fig = Figure(figsize=(4.2 * max(1, len(envs)), 3.4), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, max(1, len(envs)), squeeze=False)[0]
    for ax, env in zip(axes, envs, strict=False):
        for (e, model, planner), by_step in sorted(curves.items()):
            if e != env:
                continue
            steps = sorted(by_step)
            mu = [statistics.fmean(by_step[t]) for t in steps]
            sd = [statistics.pstdev(by_step[t]) for t in steps]
            line = ax.plot(steps, mu, marker="o", ms=3, label=f"{model} + {planner}")[0]
            ax.fill_between(
                steps,
                [m - d for m, d in zip(mu, sd, strict=True)],
                [m + d for m, d in zip(mu, sd, strict=True)],
                color=line.get_color(),
                alpha=0.2,
            )
            oracle = [
                float(s["oracle_return_mean"])
                for s in summaries
                if (s["env"], s["model"], s["planner"]) == (e, model, planner)
            ]
            ax.axhline(
                statistics.fmean(oracle),
                color=line.get_color(),
                ls=":",
                lw=1.2,
                label=f"oracle: {planner} on MuJoCo",
            )
        ax.set(title=env, xlabel="env steps", ylabel="evaluation return")
        ax.legend(fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("roots", nargs="+", type=Path, help="folders holding run dirs")
    parser.add_argument("--figure", type=Path, default=None, help="write a PNG of the curves")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    missing = [r for r in args.roots if not r.is_dir()]
    if missing:
        log.error("not a folder: %s", ", ".join(map(str, missing)))
        return 2
    summaries, incomplete = find_runs(args.roots)
    log.info("%s", table(summaries))
    for run in incomplete:
        log.info("incomplete run (no %s): %s", SUMMARY, run)
    if args.figure is not None and summaries:
        log.info("figure: %s", figure(summaries, args.figure))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
