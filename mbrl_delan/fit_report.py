"""`python -m mbrl_delan.fit_report RUN... [options]`: compare inverse-dynamics fits.

Reads the runs of `python -m mbrl_delan.fit` (every folder at or below the given paths that
holds a ``summary.json`` from it), draws their training and validation torque MSE per epoch
on the same axes (``--figure``; the paper's figure: DeLaN against the feed-forward network)
and prints a Markdown table of the final MSE per model and split (``--table``, the default
when nothing else is asked for); ``--seeds``: mean and 95% CI over seeds per model and split,
and each model's paired difference to the feed-forward network on the same seeds;
``--clips``: the final errors per clip of every split.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from mbrl_delan.stops import stop_line
from mbrl_delan.training.recorder import METRICS_FILE, SUMMARY_FILE, read_metrics

log = logging.getLogger(__name__)

SPLIT_ORDER = ("train", "val", "val_time", "val_clip", "test")  # mocap and arrays splits


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


def clip_table(runs: list[dict[str, Any]]) -> str:
    """Markdown: one row per run, split and clip (or trajectory), the final errors on its
    samples (``final.<split>.clips`` or ``.trajectories`` of summary.json; runs written
    before them have no rows)."""
    lines = [
        "| model | seed | split | clip or trajectory | samples | MSE (normalised) | MSE (SI) "
        "| R^2 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in runs:
        for split in SPLIT_ORDER:
            final = s["final"].get(split, {})
            for clip, part in final.get("clips", final.get("trajectories", {})).items():
                lines.append(
                    f"| {_label(s, runs)} | {s.get('seed')} | {split} | {clip} | {part['n']} "
                    f"| {part['mse']:.4g} | {part['mse_si']:.4g} | {part['r2']:.3f} |"
                )
    return "\n".join(lines)


def _metric(summary: dict[str, Any], split: str, key: str) -> float | None:
    part = summary["final"].get(split)
    if part is None:
        return None
    if key == "root_mse":
        return part.get("groups", {}).get("root", {}).get("mse")
    return part.get(key)


SEED_METRICS = (("mse", "MSE (normalised)"), ("joint_mse_si", "joint MSE (SI)"),
                ("root_mse", "root MSE (normalised)"), ("r2", "R^2"))  # fmt: skip


def seed_table(runs: list[dict[str, Any]], baseline: str = "mlp") -> str:
    """Markdown: per model and split, mean +- 95% CI half-width (Student t) over seeds of the
    final errors; then, for every other model, its difference to ``baseline`` on the same
    seeds (paired: the data split is the same for every seed)."""
    from mbrl_delan.report import mean_ci

    models = list(dict.fromkeys(s["model"] for s in runs))
    head = " | ".join(label for _, label in SEED_METRICS)
    lines = [f"| model | split | seeds | {head} |", "|---|---|---|" + "---|" * len(SEED_METRICS)]
    for model in models:
        mine = [s for s in runs if s["model"] == model]
        for split in SPLIT_ORDER:
            cells = [_pm(*mean_ci(_values(mine, split, key))) for key, _ in SEED_METRICS]
            lines.append(f"| {model} | {split} | {len(mine)} | " + " | ".join(cells) + " |")
    by_seed = {s.get("seed"): s for s in runs if s["model"] == baseline}
    others = [m for m in models if m != baseline]
    if by_seed and others:
        lines += ["", f"Difference to {baseline} on the same seeds (negative: lower error):", ""]
        lines += [f"| model | split | pairs | {head} |", lines[1]]
        for model in others:
            pairs = [(s, by_seed[s.get("seed")]) for s in runs
                     if s["model"] == model and s.get("seed") in by_seed]  # fmt: skip
            for split in SPLIT_ORDER:
                cells = []
                for key, _ in SEED_METRICS:
                    diff = [a - b for a, b in (
                        (_metric(x, split, key), _metric(y, split, key)) for x, y in pairs
                    ) if a is not None and b is not None]  # fmt: skip
                    cells.append(_pm(*mean_ci(diff)))
                lines.append(f"| {model} | {split} | {len(pairs)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _values(runs: list[dict[str, Any]], split: str, key: str) -> list[float]:
    return [v for v in (_metric(s, split, key) for s in runs) if v is not None]


def _pm(mean: float | None, half: float | None) -> str:
    if mean is None:
        return "n/a"
    return f"{mean:.4g}" if half is None else f"{mean:.4g} ± {half:.2g}"


def figure(runs: list[dict[str, Any]], path: Path) -> Path | None:
    """Every run's train and validation curves on shared axes (normalised and SI MSE)."""
    from mbrl_delan.training.fit_plots import plot_loss_curves

    curves = {_label(s, runs): read_metrics(Path(s["run_dir"]) / METRICS_FILE) for s in runs}
    return plot_loss_curves(curves, path, title=_title(runs))


def _title(runs: list[dict[str, Any]]) -> str:
    """``Inverse dynamics, <data>: <models>, seed(s) <seeds>`` of the runs drawn."""
    data = ", ".join(sorted({str(s.get("data")) for s in runs}))
    models = ", ".join(sorted({str(s["model"]) for s in runs}))
    seeds = sorted({int(s["seed"]) for s in runs if s.get("seed") is not None})
    seed = ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(map(str, seeds))
    return f"Inverse dynamics, {data}: {models}, {seed}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "runs", nargs="+", type=Path, help="run dirs of mbrl_delan.fit, or folders above them"
    )
    parser.add_argument("--figure", type=Path, default=None, help="write the loss curves (PNG)")
    parser.add_argument("--table", action="store_true", help="print the Markdown table")
    parser.add_argument("--clips", action="store_true", help="print the errors per clip")
    parser.add_argument(
        "--seeds",
        action="store_true",
        help="print mean +- 95%% CI over seeds per model, and the paired difference to the mlp",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    missing = [r for r in args.runs if not r.is_dir()]
    if missing:
        stop_line("not a folder", ", ".join(map(str, missing)))
        return 2
    runs = find_fit_runs(args.runs)
    if not runs:
        folders = ", ".join(map(str, args.runs))
        stop_line("no runs", f"no run of mbrl_delan.fit (no {SUMMARY_FILE} with final errors) "
                  f"in {folders}")  # fmt: skip
        return 2
    if args.table or (args.figure is None and not args.seeds and not args.clips):
        sys.stdout.write(table(runs) + "\n")  # the command's output, for piping into a file
    if args.seeds:
        sys.stdout.write(seed_table(runs) + "\n")
    if args.clips:
        sys.stdout.write(clip_table(runs) + "\n")
    if args.figure is not None:
        written = figure(runs, args.figure)
        log.info("figure: %s", written if written else "nothing to draw (no metrics)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
