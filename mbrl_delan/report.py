"""`python -m mbrl_delan.report DIR [DIR ...]`: a table of runs' returns against the oracle.

Reads every `summary.json` below the given folders, groups runs by (env, model, planner) and
prints a Markdown table of mean and std over seeds of the final evaluation return, the
oracle return and their ratio. Run dirs without a `summary.json` are listed as incomplete.
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("roots", nargs="+", type=Path, help="folders holding run dirs")
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
