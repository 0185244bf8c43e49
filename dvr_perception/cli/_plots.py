"""Figures of the ``measure`` command: deviation maps, visibility histograms and the region map.

Every helper builds a :class:`matplotlib.figure.Figure` on an explicit Agg canvas (no pyplot, no
global backend switch) and writes it through :func:`dvr_perception._files.atomic_path`, so a
failed write never leaves a partial PNG.  Matplotlib is imported lazily: it is a CLI-only
dependency and the core package never imports it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dvr_perception._files import atomic_path

__all__ = ["save_deviation_map", "save_region_map", "save_visibility_histograms"]

#: Colour of pixels outside the measured area (empty rays) in the deviation maps.
EMPTY_COLOUR = "#d0d0d0"
DPI = 100


def _figure(width: float, height: float):
    """Return a constrained-layout figure attached to an Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path) -> Path:
    """Write ``fig`` as a PNG (atomically) and return the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return Path(path)


def _image_size(shape) -> tuple[float, float]:
    """Figure size (inches) for an image panel of ``shape`` (H, W) plus a colour bar."""
    h, w = int(shape[0]), int(shape[1])
    scale = 5.0 / max(h, w)
    return max(3.5, w * scale + 1.4), max(3.0, h * scale + 0.8)


def save_deviation_map(
    path,
    deviation,
    *,
    title: str,
    vmin: float,
    vmax: float,
    mask=None,
    label: str = "deviation",
    cmap: str = "viridis",
) -> Path:
    """Write a colour-mapped deviation image with a colour bar and a title.

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    deviation : array_like, shape (H, W)
        Per-pixel deviation (row 0 at the top).
    title : str
        Figure title (typically names the measure and gives its E value).
    vmin, vmax : float
        Fixed colour scale; values outside are clipped to the end colours.
    mask : array_like of bool, shape (H, W), optional
        Pixels that were measured; the others are drawn in :data:`EMPTY_COLOUR`.
    label : str, optional
        Colour-bar label.
    cmap : str, optional
        Matplotlib colour map name.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    import matplotlib as mpl

    values = np.asarray(deviation, dtype=float)
    shown = values if mask is None else np.ma.masked_where(~np.asarray(mask, bool), values)
    colours = mpl.colormaps[cmap].with_extremes(bad=EMPTY_COLOUR)
    fig = _figure(*_image_size(values.shape))
    ax = fig.add_subplot()
    im = ax.imshow(shown, cmap=colours, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, shrink=0.85, label=label)
    return _save(fig, path)


def save_visibility_histograms(path, per_structure: dict, bin_edges, *, title: str) -> Path:
    """Write one panel per structure: histograms of its per-ray visible and assigned shares.

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    per_structure : dict
        ``VisibilityResult.per_structure``: ``name -> {"histogram_visible",
        "histogram_assigned", "visible_share", "assigned_share", "rays"}``.
    bin_edges : array_like
        Histogram bin edges on [0, 1].
    title : str
        Figure title.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    edges = np.asarray(bin_edges, dtype=float)
    centres = 0.5 * (edges[:-1] + edges[1:])
    width = np.diff(edges)
    names = list(per_structure)
    k = max(len(names), 1)
    cols = min(k, 3)
    rows = -(-k // cols)
    fig = _figure(3.6 * cols, 2.8 * rows + 0.5)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax in axes[len(names) :]:
        ax.set_axis_off()
    for ax, name in zip(axes, names, strict=False):
        entry = per_structure[name]
        rays = int(entry["rays"])
        vis = np.asarray(entry["histogram_visible"], float)
        asg = np.asarray(entry["histogram_assigned"], float)
        frac_v = vis / rays if rays else vis
        frac_a = asg / rays if rays else asg
        ax.bar(centres - width / 4, frac_a, width / 2, color="#4c72b0", label="assigned share")
        ax.bar(centres + width / 4, frac_v, width / 2, color="#dd8452", label="visible share")
        ax.set_xlim(0.0, 1.0)
        ax.set_xlabel("per-ray share", fontsize=8)
        ax.set_ylabel("fraction of rays", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(
            f"{name}: visible {entry['visible_share']:.3f} / assigned "
            f"{entry['assigned_share']:.3f} ({rays} rays)",
            fontsize=8,
        )
    if names:
        axes[0].legend(fontsize=7, loc="upper center")
    else:
        axes[0].text(0.5, 0.5, "no structures", ha="center", va="center")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _region_colours(n: int) -> np.ndarray:
    """``n`` distinguishable RGB colours (tab20, then a hue wheel for more)."""
    import matplotlib as mpl

    tab20 = np.asarray(mpl.colormaps["tab20"].colors)
    base = np.concatenate([tab20[::2], tab20[1::2]])  # ten distinct hues first
    if n <= len(base):
        return base[:n]
    hues = np.linspace(0.0, 1.0, n, endpoint=False)
    return mpl.colors.hsv_to_rgb(np.stack([hues, np.full(n, 0.65), np.full(n, 0.9)], axis=1))


def save_region_map(path, region_id, regions: list, *, title: str, empty_colour=(0, 0, 0)) -> Path:
    """Write the sub-region map: one colour per layer set, region borders, named legend.

    Sub-regions with the same layer set share a colour (the legend names its layers, the
    number of connected regions and the area); the borders between connected regions are
    drawn in white, so separate regions of the same set stay distinguishable.

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    region_id : array_like of int, shape (H, W)
        ``TransparencyResult.region_id``.
    regions : list of dict
        ``TransparencyResult.regions`` (``id``, ``layers``, ``kind``, ``area_fraction``).
    title : str
        Figure title.
    empty_colour : tuple of 3 float, optional
        Colour of the empty (no layer) regions.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    from matplotlib.patches import Patch

    rid = np.asarray(region_id, dtype=np.int64)
    keys, groups = [], {}
    for r in regions:
        key = tuple(r["layers"])
        if key not in groups:
            keys.append(key)
            groups[key] = {"ids": [], "area": 0.0}
        groups[key]["ids"].append(int(r["id"]))
        groups[key]["area"] += float(r["area_fraction"])
    non_empty = [key for key in keys if key]
    colours = dict(zip(non_empty, _region_colours(len(non_empty)), strict=True))
    colours[()] = np.asarray(empty_colour, float)
    table = np.zeros((max(len(regions), int(rid.max(initial=0)) + 1), 3))
    for key in keys:
        table[groups[key]["ids"]] = colours[key]
    rgb = table[rid]
    border = np.zeros(rid.shape, bool)
    border[:-1] |= rid[:-1] != rid[1:]
    border[:, :-1] |= rid[:, :-1] != rid[:, 1:]
    rgb[border] = 1.0
    h, w = rid.shape
    scale = 5.0 / max(h, w)
    fig = _figure(w * scale + 3.6, max(3.0, h * scale + 0.8))
    ax = fig.add_subplot()
    ax.imshow(rgb, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    handles = []
    for key in keys:
        g = groups[key]
        label = "{" + ", ".join(key) + "}" if key else "empty"
        n = len(g["ids"])
        label += f"  ({n} region{'s' if n != 1 else ''}, {g['area']:.2%})"
        handles.append(Patch(facecolor=colours[key], edgecolor="0.5", label=label))
    fig.legend(handles=handles, loc="outside right center", fontsize=7, frameon=False)
    return _save(fig, path)
