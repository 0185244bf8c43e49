"""Figures of the CLI: deviation maps, visibility histograms, region map, convergence plot.

Every helper builds a :class:`matplotlib.figure.Figure` on an explicit Agg canvas (no pyplot, no
global backend switch) and writes it through :func:`dvr_perception._files.atomic_path`, so a
failed write never leaves a partial PNG.  Matplotlib is imported lazily: it is a CLI-only
dependency and the core package never imports it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dvr_perception._figures import DPI as DPI  # re-export
from dvr_perception._figures import EMPTY_COLOUR
from dvr_perception._figures import new_figure as _figure
from dvr_perception._figures import save_png as _save

__all__ = [
    "MEASURE_FIGURES",
    "plot_text",
    "save_convergence",
    "save_deviation_map",
    "save_measure_figures",
    "save_region_map",
    "save_side_by_side",
    "save_visibility_histograms",
]

#: Longest structure name drawn in a figure (characters; longer names end in ``…``).
PLOT_NAME_LENGTH = 32
#: Most layer sets the region map's legend lists (the rest are counted in one entry).
MAX_LEGEND = 24


def plot_text(name, limit: int = PLOT_NAME_LENGTH) -> str:
    r"""``name`` as figure text: escaped, cut to ``limit`` characters, ``$`` kept literal.

    Matplotlib reads text between two ``$`` as mathematics (a bad formula fails the whole
    figure), so every ``$`` is escaped; non-printable characters are escaped as in
    :func:`dvr_perception.structures.spec.printable`.

    Examples
    --------
    >>> print(plot_text("cost $5 $"))
    cost \$5 \$
    >>> len(plot_text("x" * 1000))
    32
    """
    from dvr_perception.structures.spec import printable

    return printable(name, limit).replace("$", r"\$")


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
    fw, fh = _image_size(values.shape)
    h, w = values.shape[:2]
    scale = 5.0 / max(h, w)
    iw, ih = w * scale, h * scale  # the image panel, inches; margins as _image_size gives
    fig = _figure(fw, fh, layout=None)
    left = (fw - 1.4 - iw) / 2 + 0.1
    ax = fig.add_axes((left / fw, 0.15 / fh, iw / fw, ih / fh))
    im = ax.imshow(shown, cmap=colours, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    bar = fig.add_axes(((left + iw + 0.25) / fw, (0.15 + 0.075 * ih) / fh, 0.18 / fw,
                        0.85 * ih / fh))  # fmt: skip
    fig.colorbar(im, cax=bar, label=label)
    return _save(fig, path)


def save_visibility_histograms(path, per_structure: dict, bin_edges, *, title: str) -> Path:
    """Write one panel per structure: histograms of its per-ray visible and target opacities.

    Decision D1: ``histogram_visible`` counts the per-ray visible opacity ``alpha_v`` and
    ``histogram_assigned`` the per-ray target opacity ``alpha_o``; the title gives the
    structure's image-wide share of the picture against its target share.

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    per_structure : dict
        ``VisibilityResult.per_structure``: ``name -> {"histogram_visible",
        "histogram_assigned", "visible_share", "target_share", "rays"}``.
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
    names = list(per_structure)
    k = max(len(names), 1)
    cols = min(k, 3)
    rows = -(-k // cols)
    fw, fh = 3.6 * cols, 2.8 * rows + 0.5
    fig = _figure(fw, fh, layout=None)
    fig.subplots_adjust(left=0.55 / fw, right=1 - 0.15 / fw, bottom=0.5 / fh, top=1 - 0.75 / fh,
                        wspace=0.35, hspace=0.6)  # fmt: skip
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
        # one step artist per histogram (hundreds of bar patches drew ten times slower)
        ax.stairs(frac_a, edges, fill=True, color="#4c72b0", alpha=0.45, label="target opacity")
        ax.stairs(frac_v, edges, color="#dd8452", linewidth=1.6, label="visible opacity")
        ax.set_xlim(0.0, 1.0)
        ax.set_xlabel("per-ray opacity", fontsize=8)
        ax.set_ylabel("fraction of rays", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(
            f"{plot_text(name)}: share {entry['visible_share']:.3f} / target "
            f"{entry['target_share']:.3f} ({rays} rays)",
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
    shown = sorted(keys, key=lambda k: -groups[k]["area"])[:MAX_LEGEND]  # the largest sets
    for key in [k for k in keys if k in shown]:
        g = groups[key]
        label = "{" + ", ".join(plot_text(name, 20) for name in key) + "}" if key else "empty"
        n = len(g["ids"])
        label += f"  ({n} region{'s' if n != 1 else ''}, {g['area']:.2%})"
        handles.append(Patch(facecolor=colours[key], edgecolor="0.5", label=label))
    if len(keys) > len(shown):
        rest = sum(groups[k]["area"] for k in keys if k not in shown)
        more = f"{len(keys) - len(shown)} more layer sets ({rest:.2%})"
        handles.append(Patch(facecolor="none", edgecolor="none", label=more))
    fig.legend(handles=handles, loc="outside right center", fontsize=7, frameon=False)
    return _save(fig, path)


#: Terms drawn by :func:`save_convergence`, with their colours.
CONVERGENCE_TERMS = (
    ("E_v", "#4c72b0"),
    ("E_s", "#dd8452"),
    ("E_t", "#55a868"),
    ("E", "#222222"),
)


def save_convergence(path, stages, *, title: str) -> Path:
    """Write the optimiser's terms per iteration across its stages, stage boundaries marked.

    Parameters
    ----------
    path : str or os.PathLike
        Output PNG.
    stages : sequence of dict
        One entry per stage, in order: ``name``; ``history``, a sequence of term dicts (keys
        ``E_v``, ``E_s``, ``E_t``, ``E``; one per iteration, at the optimisation resolution);
        optionally ``before`` and ``after``, term dicts at the user's resolution, drawn as
        markers of ``E`` at the stage boundaries.
    title : str
        Figure title.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    fig = _figure(7.5, 4.2)
    ax = fig.add_subplot()
    start = 0
    marked = False
    for k, stage in enumerate(stages):
        history = list(stage.get("history") or ())
        x = np.arange(start + 1, start + len(history) + 1)
        before = stage.get("before")
        first = [before] if before is not None else []
        xs = np.concatenate([[start], x]) if first else x
        for term, colour in CONVERGENCE_TERMS:
            ys = [float(h[term]) for h in [*first, *history]]
            if ys:
                ax.plot(xs, ys, color=colour, lw=2.0 if term == "E" else 1.3,
                        label=term if k == 0 else None)  # fmt: skip
        for at, terms in ((start, before), (start + len(history), stage.get("after"))):
            if terms is not None:
                ax.plot([at], [float(terms["E"])], "o", mfc="white", mec="#222222",
                        label=None if marked else "E at the user's resolution")  # fmt: skip
                marked = True
        if k:
            ax.axvline(start, color="0.6", ls="--", lw=1.0)
        ax.text(start + max(len(history), 1) / 2, 1.01, plot_text(stage["name"]), ha="center",
                va="bottom", fontsize=8, transform=ax.get_xaxis_transform())  # fmt: skip
        start += len(history)
    ax.set_xlim(0, max(start, 1))
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("iteration (all stages)", fontsize=9)
    ax.set_ylabel("deviation (lower is better)", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(title, fontsize=10, pad=16)
    return _save(fig, path)


#: Files of :func:`save_measure_figures` (after its prefix).
MEASURE_FIGURES = (
    "visibility_deviation.png",
    "shape_deviation.png",
    "transparency_deviation.png",
    "visibility_histograms.png",
    "regions.png",
)


def save_measure_figures(out_dir, prefix: str, measures) -> list[Path]:
    """Write the ``measure`` figures of ``(visibility, shape, transparency)`` results.

    The files are :data:`MEASURE_FIGURES` in ``out_dir``, each name prefixed ``{prefix}_``.

    Returns
    -------
    list of pathlib.Path
        The written paths.
    """
    out_dir = Path(out_dir)
    vis, shp, trn = measures
    t_max = max(1e-3, float(np.max(trn.deviation, initial=0.0)))
    maps = (
        (vis.deviation, f"δ_v (E_v = {vis.E_v:.4f})", 2.0, vis.nonempty, "δ_v"),
        (shp.deviation, f"δ_s (E_s = {shp.E_s:.4f})", 1.0, shp.nonempty, "δ_s"),
        (trn.deviation, f"δ_t (E_t = {trn.E_t:.4f})", t_max, np.asarray(trn.layer_set) != 0, "δ_t"),
    )
    files = []
    for name, (dev, title, vmax, mask, label) in zip(MEASURE_FIGURES[:3], maps, strict=True):
        files.append(
            save_deviation_map(
                out_dir / f"{prefix}_{name}",
                dev,
                title=f"{prefix}: {title}",
                vmin=0.0,
                vmax=vmax,
                mask=mask,
                label=label,
            )
        )
    files.append(
        save_visibility_histograms(
            out_dir / f"{prefix}_{MEASURE_FIGURES[3]}",
            vis.per_structure,
            vis.bin_edges,
            title=f"{prefix}: assigned vs visible share per ray (E_v = {vis.E_v:.4f})",
        )
    )
    files.append(
        save_region_map(
            out_dir / f"{prefix}_{MEASURE_FIGURES[4]}",
            trn.region_id,
            trn.regions,
            title=f"{prefix}: sub-regions by layer set ({len(trn.regions)} regions)",
        )
    )
    return files


def save_side_by_side(path, images, titles) -> Path:
    """Write two RGB images (floats in [0, 1], row 0 at the top) side by side with titles."""
    h, w = np.asarray(images[0]).shape[:2]
    scale = 4.5 / max(h, w)
    fig = _figure(2 * w * scale + 0.4, h * scale + 0.7)
    for i, (image, title) in enumerate(zip(images, titles, strict=True)):
        ax = fig.add_subplot(1, 2, i + 1)
        ax.imshow(np.clip(image, 0.0, 1.0), interpolation="nearest")
        ax.set_axis_off()
        ax.set_title(title, fontsize=9)
    return _save(fig, path)
