"""The common form of the project's figures: page width, type readable at page width, legends
outside the data, and the smallest type size written into the PNG.

A figure is `PAGE_WIDTH_IN` inches wide, so that on a documentation page (about 700 px of
content) one point of type is about 1.5 px and `MIN_FONT_PT` is at least the body text's
16 px. `save_figure` raises every text of the figure (titles, labels, ticks, legends) to
`MIN_FONT_PT` and records the smallest size and the figure's width in the PNG's text chunks
(`FONT_KEY`, `WIDTH_KEY`), which the site check reads (``tools/check_site.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

PAGE_WIDTH_IN = 6.4
MIN_FONT_PT = 11.0
DPI = 150
FONT_KEY = "mbrl_delan:min_font_pt"
WIDTH_KEY = "mbrl_delan:width_in"


def page_figure(height_in: float, nrows: int = 1, ncols: int = 1) -> tuple[Figure, Any]:
    """A page-wide figure with an (nrows, ncols) array of axes, laid out by matplotlib's
    constrained layout (which makes room for a legend placed outside, `legend_below`)."""
    fig = Figure(figsize=(PAGE_WIDTH_IN, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=False)


def legend_below(fig: Figure, ncols: int = 2) -> None:
    """One legend for the whole figure, below the axes and outside them: every label of
    every axes once (the same label on two panels must be drawn in one colour)."""
    entries: dict[str, Any] = {}
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    if entries:
        fig.legend(
            list(entries.values()),
            list(entries),
            loc="outside lower center",
            ncols=min(ncols, len(entries)),
            frameon=False,
        )


def save_figure(fig: Figure, path: str | Path, dpi: int = DPI) -> Path:
    """Raise every text to `MIN_FONT_PT`, then write the PNG with its smallest type size
    and width in its metadata. -> the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    for ax in fig.axes:
        ax.tick_params(which="both", labelsize=MIN_FONT_PT)
    fig.canvas.draw()  # creates the tick labels and the legends' texts
    texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]
    for text in texts:
        text.set_fontsize(max(text.get_fontsize(), MIN_FONT_PT))
    smallest = min((t.get_fontsize() for t in texts), default=MIN_FONT_PT)
    width = fig.get_figwidth()
    fig.savefig(path, dpi=dpi, metadata={FONT_KEY: f"{smallest:g}", WIDTH_KEY: f"{width:g}"})
    return path
