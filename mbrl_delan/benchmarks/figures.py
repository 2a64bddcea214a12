"""`python -m mbrl_delan.benchmarks.figures FILE [FILE ...] --out PNG`: suite humanoid's
error-vs-horizon figure.

Reads the JSON Lines records of `python -m mbrl_delan.bench suite=humanoid out=FILE` and draws
`rollout_error` against its `horizon`, one line per case (`{model}-n{transitions}`, with the
K of its rollout loss), on a log scale. Where a case has several records at a horizon (runs
with other `seed=`s), the line is their mean and a band spans their smallest to largest; the
log lists each point as mean, min, max and count. Exit status 2 when a file is missing or
malformed or holds no `rollout_error` record.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any

from mbrl_delan.benchmarks.records import read_records
from mbrl_delan.figure_style import legend_below, page_figure, save_figure
from mbrl_delan.stops import stop_line

log = logging.getLogger(__name__)

ROLLOUT_ERROR = "rollout_error"


def error_curves(records: list[dict[str, Any]]) -> dict[str, list[tuple[int, list[float]]]]:
    """Case label -> [(horizon, its rollout_error values)] sorted by horizon (records without a
    value left out). The label is the case, with `K=` its rollout loss's steps when recorded;
    a horizon holds one value per record (one per seed run)."""
    curves: dict[str, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        if r.get("metric") != ROLLOUT_ERROR or r.get("value") is None:
            continue
        if not isinstance(r.get("case"), str) or not isinstance(r.get("horizon"), int):
            raise ValueError(f"a {ROLLOUT_ERROR} record without its case or horizon: {r}")
        steps = r.get("rollout_steps")
        label = r["case"] if steps is None else f"{r['case']} (K={steps})"
        curves[label][int(r["horizon"])].append(float(r["value"]))
    return {label: sorted(by_h.items()) for label, by_h in sorted(curves.items())}


def describe_curves(curves: dict[str, list[tuple[int, list[float]]]], x: str = "h") -> list[str]:
    """One line per case and x (a horizon): `case h=H mean M (min A, max B, n N)`."""
    return [
        f"{label} {x}={h}: mean {statistics.fmean(v):.4g} (min {min(v):.4g}, "
        f"max {max(v):.4g}, n {len(v)})"
        for label, points in curves.items()
        for h, v in points
    ]


def read_record_files(paths: list[Path]) -> list[dict[str, Any]] | None:
    """The records of every file; None (the reason logged) when one cannot be read."""
    records: list[dict[str, Any]] = []
    for path in paths:
        try:
            records += read_records(path)
        except (OSError, json.JSONDecodeError) as err:
            stop_line("cannot read records", f"{path}: {err}")
            return None
    return records


def plot_error_curves(
    curves: dict[str, list[tuple[int, list[float]]]],
    path: Path,
    title: str,
    xlabel: str = "horizon (control steps, open loop)",
    ylabel: str = "rollout_error (normalised RMS)",
    xlog: bool = False,
) -> Path:
    """Draw the curves (log y; `xlog`: log x too) into the PNG at `path`: the mean, and the
    min-max band where an x has several values."""
    fig, axes = page_figure(4.4)
    ax = axes[0, 0]
    for label, points in curves.items():
        h = [p[0] for p in points]
        runs = max(len(v) for _, v in points)
        name = label if runs == 1 else f"{label}, mean of {runs}"
        (line,) = ax.plot(h, [statistics.fmean(v) for _, v in points], marker="o", label=name)
        if runs > 1:
            lo, hi = [min(v) for _, v in points], [max(v) for _, v in points]
            ax.fill_between(h, lo, hi, color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_yscale("log")
    if xlog:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    fig.suptitle(title)
    ax.grid(True, which="both", alpha=0.3)
    legend_below(fig)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", type=Path, help="records of suite humanoid (JSONL)")
    parser.add_argument("--out", type=Path, required=True, help="the figure to write (PNG)")
    parser.add_argument("--title", default="Humanoid-v5: open-loop rollout error")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    records = read_record_files(args.files)
    if records is None:
        return 2
    try:
        curves = error_curves(records)
    except ValueError as err:
        stop_line("bad input", err)
        return 2
    if not curves:
        stop_line("no records", f"no {ROLLOUT_ERROR} records in {', '.join(map(str, args.files))}")
        return 2
    for line in describe_curves(curves):
        log.info("%s", line)
    log.info("figure: %s", plot_error_curves(curves, args.out, args.title))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
