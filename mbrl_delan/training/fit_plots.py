"""Loss curves of inverse-dynamics fits: torque MSE per epoch, train and validation, log axes.

Reads the per-epoch records of ``metrics.jsonl`` (`mbrl_delan.training.inverse_fit`:
``<split>_mse`` normalised, ``<split>_mse_si`` in SI units). One colour per run (model), one
line style per split: training solid, held-out time segments dashed, held-out clips dotted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mbrl_delan.figure_style import legend_below, page_figure, save_figure

LOSS_CURVES_PNG = "loss_curves.png"
EPOCH = "epoch"
SPLIT_STYLES = {"train": "-", "val_time": "--", "val_clip": ":"}
SPLIT_LABELS = {
    "train": "train",
    "val_time": "val: held-out segments",
    "val_clip": "val: held-out clips",
}
METRIC_LABELS = {  # (panel title, y label)
    "mse": ("torque MSE, normalised per DoF", "MSE"),
    "mse_si": ("torque MSE in SI units (N$^2$m$^2$; N$^2$ for the root force)", "MSE"),
}


def _curve(records: list[dict[str, Any]], key: str) -> tuple[list[float], list[float]]:
    """(epoch, value) of the records with a positive finite value for key."""
    pairs = sorted(
        (float(r[EPOCH]), float(r[key]))
        for r in records
        if isinstance(r.get(EPOCH), int | float)
        and isinstance(r.get(key), int | float)
        and math.isfinite(r[key])
        and r[key] > 0
    )
    return [p[0] for p in pairs], [p[1] for p in pairs]


def plot_loss_curves(
    runs: Mapping[str, list[dict[str, Any]]],
    path: Path,
    metrics: tuple[str, ...] = ("mse", "mse_si"),
    title: str | None = None,
) -> Path | None:
    """One panel per metric, stacked; every run (label -> metrics records) and split on each
    panel, one legend below.

    Returns the PNG's path, or None when no run has any curve.
    """
    fig, panels = page_figure(0.8 + 3.0 * len(metrics), len(metrics), 1)
    axes = panels[:, 0]
    drawn = 0
    colors = [f"C{i}" for i in range(10)]
    for ax, metric in zip(axes, metrics, strict=True):
        for i, (label, records) in enumerate(runs.items()):
            for split, style in SPLIT_STYLES.items():
                x, y = _curve(records, f"{split}_{metric}")
                if not x:
                    continue
                ax.plot(
                    x,
                    y,
                    style,
                    color=colors[i % len(colors)],
                    label=f"{label}: {SPLIT_LABELS[split]}",
                )
                drawn += 1
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        panel, ylabel = METRIC_LABELS.get(metric, (metric, metric))
        ax.set(title=panel, ylabel=ylabel)
        ax.grid(True, which="both", alpha=0.3)
    if not drawn:
        return None
    if title:
        fig.suptitle(title)
    legend_below(fig, ncols=2)
    return save_figure(fig, path)
