"""`python -m mbrl_delan.fit_report RUN... [--figure PNG] [--table]`: compare inverse-dynamics fits.

Reads the runs of `python -m mbrl_delan.fit` (every folder at or below the given paths that
holds a ``summary.json`` from it), draws their training and validation torque MSE per epoch
on the same axes (``--figure``; the paper's figure: DeLaN against the feed-forward network)
and prints a Markdown table of the final MSE per model and split (``--table``, the default
when no figure is asked for).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from mbrl_delan.training.recorder import METRICS_FILE, SUMMARY_FILE, read_metrics

log = logging.getLogger(__name__)

SPLIT_ORDER = ("train", "val_time", "val_clip")


def find_fit_runs(paths: list[Path]) -> list[dict[str, Any]]:
    """Summaries of fit runs at or below ``paths`` (with ``run_dir`` added), in path order."""
    out: list[dict[str, Any]] = []
    for root in paths:
        candidates = [root / SUMMARY_FILE] if (root / SUMMARY_FILE).is_file() else []
        candidates += sorted(p for p in root.rglob(SUMMARY_FILE) if p.parent != root)
        for path in candidates:
            summary = json.loads(path.read_text())
            if isinstance(summary, dict) and "final" in summary and "model" in summary:
                out.append({**summary, "run_dir": str(path.parent)})
    return out


def _label(summary: dict[str, Any], all_runs: list[dict[str, Any]]) -> str:
    """The model's name, with the seed (and then the folder) when that is ambiguous."""
    same = [s for s in all_runs if s["model"] == summary["model"]]
    if len(same) == 1:
        return str(summary["model"])
    label = f"{summary['model']} s{summary.get('seed')}"
    if sum(1 for s in same if s.get("seed") == summary.get("seed")) > 1:
        label += f" ({Path(summary['run_dir']).name})"
    return label


def table(runs: list[dict[str, Any]]) -> str:
    """Markdown: one row per run and split, final errors."""
    lines = [
        "| model | seed | epochs | split | samples | MSE (normalised) | MSE (SI) "
        "| joint MSE (SI) | R^2 | wall time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in runs:
        for split in SPLIT_ORDER:
            part = s["final"].get(split)
            if part is None:
                continue
            lines.append(
                f"| {_label(s, runs)} | {s.get('seed')} | {s.get('epochs')} | {split} "
                f"| {part['n']} | {part['mse']:.4g} | {part['mse_si']:.4g} "
                f"| {part['joint_mse_si']:.4g} | {part['r2']:.3f} "
                f"| {s.get('wall_time_s', float('nan')):.0f} |"
            )
    return "\n".join(lines)


def figure(runs: list[dict[str, Any]], path: Path) -> Path | None:
    """Every run's train and validation curves on shared axes (normalised and SI MSE)."""
    from mbrl_delan.training.fit_plots import plot_loss_curves

    curves = {_label(s, runs): read_metrics(Path(s["run_dir"]) / METRICS_FILE) for s in runs}
    return plot_loss_curves(curves, path, title="Inverse dynamics from CMU mocap")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "runs", nargs="+", type=Path, help="run dirs of mbrl_delan.fit, or folders above them"
    )
    parser.add_argument("--figure", type=Path, default=None, help="write the loss curves (PNG)")
    parser.add_argument("--table", action="store_true", help="print the Markdown table")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    missing = [r for r in args.runs if not r.is_dir()]
    if missing:
        log.error("not a folder: %s", ", ".join(map(str, missing)))
        return 2
    runs = find_fit_runs(args.runs)
    if not runs:
        log.error(
            "no runs of mbrl_delan.fit (no %s with final errors) in %s",
            SUMMARY_FILE,
            ", ".join(map(str, args.runs)),
        )
        return 2
    if args.table or args.figure is None:
        sys.stdout.write(table(runs) + "\n")  # the command's output, for piping into a file
    if args.figure is not None:
        written = figure(runs, args.figure)
        log.info("figure: %s", written if written else "nothing to draw (no metrics)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
