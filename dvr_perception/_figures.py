"""Matplotlib figures on an explicit Agg canvas, written atomically (CLI and report figures).

No pyplot and no global backend switch: :func:`new_figure` attaches its own canvas, and
:func:`save_png` writes through :func:`dvr_perception._files.atomic_path`, so a failed write
never leaves a partial PNG.  Matplotlib is imported on first use.
"""

from __future__ import annotations

from pathlib import Path

from dvr_perception._files import atomic_path

__all__ = ["DPI", "EMPTY_COLOUR", "new_figure", "save_png"]

#: Colour of pixels outside the measured area (empty rays) in the deviation maps.
EMPTY_COLOUR = "#d0d0d0"
#: Resolution of the written PNGs (dots per inch of the figure size).
DPI = 100


def new_figure(width: float, height: float, *, layout: str | None = "constrained"):
    """Return a figure attached to an Agg canvas (constrained layout unless ``layout=None``).

    Constrained layout doubles the time of a simple figure: the image maps and the
    histograms place their axes themselves.

    Examples
    --------
    >>> fig = new_figure(2.0, 1.0)
    >>> fig.get_size_inches().tolist(), type(fig.canvas).__name__
    ([2.0, 1.0], 'FigureCanvasAgg')
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def save_png(fig, path) -> Path:
    """Write ``fig`` as a PNG at :data:`DPI` (atomically) and return the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return Path(path)
