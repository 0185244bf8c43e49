"""The report's figures: matplotlib on an explicit Agg canvas, written atomically as PNG."""
# ruff: noqa: RUF001  (figure labels use α and × on purpose)

from __future__ import annotations

from pathlib import Path

import numpy as np

from dvr_perception._figures import DPI
from dvr_perception._figures import EMPTY_COLOUR as EMPTY
from dvr_perception._figures import new_figure as _figure
from dvr_perception._figures import save_png as _save

__all__ = [
    "equalisation_figure",
    "objectives_figure",
    "performance_figure",
    "pipeline_figure",
    "saturation_figure",
    "shape_figure",
    "shares_figure",
]


def _panel(image) -> float:
    """Inches per image panel: about one figure pixel per image pixel, 2.5 to 4 inches."""
    return float(np.clip(np.asarray(image).shape[0] / DPI, 2.5, 4.0))


def _show_image(ax, image, title):
    ax.imshow(np.clip(np.asarray(image, float), 0.0, 1.0), interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=8)


def _images_over_plot(panels, title_height: float):
    """Make a figure with a row of ``(image, title)`` panels over one wide plot; return both.

    ``title_height`` (inches) leaves room for the panels' titles.
    """
    size = _panel(panels[0][0])
    fig = _figure(size * len(panels) + 0.4, size + title_height + 0.1 + 3.0)
    keys = [f"i{i}" for i in range(len(panels))]
    mosaic = fig.subplot_mosaic(
        [keys, ["plot"] * len(keys)], height_ratios=[size + title_height, 3.0]
    )
    for key, (image, title) in zip(keys, panels, strict=True):
        _show_image(mosaic[key], image, title)
    return fig, mosaic["plot"]


def _show_map(ax, values, mask, title, vmax, cmap="viridis"):
    import matplotlib as mpl

    shown = np.ma.masked_where(~np.asarray(mask, bool), np.asarray(values, float))
    im = ax.imshow(
        shown,
        cmap=mpl.colormaps[cmap].with_extremes(bad=EMPTY),
        vmin=0.0,
        vmax=vmax,
        interpolation="nearest",
    )
    ax.set_axis_off()
    ax.set_title(title, fontsize=8)
    return im


def equalisation_figure(path, exp: dict) -> Path:
    """Rows: importance ratios; columns: before, after under each composition, delta_v maps.

    The delta_v maps are those of the default (importance x presence) composition.
    """
    runs = exp["runs"]
    p = _panel(runs[0]["before"]["_images"]["image"])
    fig = _figure(5 * p + 1.2, (p + 0.6) * len(runs) + 0.4)
    axes = fig.subplots(len(runs), 5, squeeze=False)
    im = None
    for row, run in zip(axes, runs, strict=True):
        ratio = "/".join(f"{v:g}" for v in run["importance"].values())
        b, a, t = run["before"], run["after"], run["thickness"]["after"]
        _show_image(row[0], b["_images"]["image"], f"{ratio} before\n(E_v {b['E_v']:.3f})")
        _show_image(row[1], a["_images"]["image"], f"after, importance\n(E_v {a['E_v']:.3f})")
        _show_image(row[2], t["_images"]["image"], f"after, thickness\n(E_v {t['E_v']:.3f})")
        _show_map(row[3], b["_images"]["dv"], b["_images"]["dv_mask"], "δ_v before", 2.0)
        im = _show_map(row[4], a["_images"]["dv"], a["_images"]["dv_mask"], "δ_v after", 2.0)
    fig.colorbar(im, ax=axes[:, 4], shrink=0.6, label="δ_v (importance x presence target)")
    names = " / ".join(exp["structures"])
    fig.suptitle(f"{exp['dataset']}: visibility equalisation ({names} importance)", fontsize=10)
    return _save(fig, path)


def _inner_share(shares: dict, inner: str) -> float:
    return shares[inner] / max(sum(shares.values()), 1e-12)


def shares_figure(path, experiments: list) -> Path:
    """Per dataset and ratio: the inner structure's target and visible shares, both targets."""
    fig = _figure(5.2 * len(experiments), 3.8)
    axes = np.atleast_1d(fig.subplots(1, len(experiments), squeeze=False)).ravel()
    bars = (
        ("importance ratio", "#8c8c8c", lambda r: r["importance"]),
        ("target: importance x presence", "#4c72b0", lambda r: r["composition"]),
        ("target: thickness", "#64b5cd", lambda r: r["thickness_composition"]),
        ("visible before", "#c44e52", lambda r: r["before"]["visible_share"]),
        ("visible after (importance)", "#55a868", lambda r: r["after"]["visible_share"]),
        (
            "visible after (thickness)",
            "#ccb974",
            lambda r: r["thickness"]["after"]["visible_share"],
        ),
    )
    width = 0.8 / len(bars)
    for ax, exp in zip(axes, experiments, strict=True):
        inner = exp["structures"][1]
        xs = np.arange(len(exp["runs"]))
        for j, (label, colour, get) in enumerate(bars):
            ys = [_inner_share(get(run), inner) for run in exp["runs"]]
            ax.bar(xs + (j - (len(bars) - 1) / 2) * width, ys, width, color=colour, label=label)
        ax.set_xticks(
            xs, ["/".join(f"{v:g}" for v in r["importance"].values()) for r in exp["runs"]]
        )
        ax.set_ylim(0, 1)
        ax.set_xlabel(f"importance {' / '.join(exp['structures'])}", fontsize=8)
        ax.set_ylabel(f"image-wide share of '{inner}' (inner)", fontsize=8)
        ax.set_title(exp["dataset"], fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=6, loc="upper left")
    return _save(fig, path)


def objectives_figure(path, comparison: dict) -> Path:
    """Rows: datasets; columns: the original and the final image of each objective."""
    runs = comparison["runs"]
    objectives = list(next(iter(runs.values())))
    first = next(iter(next(iter(runs.values())).values()))
    p = _panel(first["steps"][0]["_images"]["image"])
    cols = 1 + len(objectives)
    fig = _figure(cols * p + 0.4, (p + 0.75) * len(runs) + 0.4)
    axes = fig.subplots(len(runs), cols, squeeze=False)
    for row, (name, by) in zip(axes, runs.items(), strict=True):
        st0 = next(iter(by.values()))["steps"][0]
        _show_image(row[0], st0["_images"]["image"], f"{name} original\n{_terms_title(st0)}")
        for ax, obj in zip(row[1:], objectives, strict=True):
            st = by[obj]["steps"][-1]
            _show_image(ax, st["_images"]["image"], f"{obj}\n{_terms_title(st)}")
    fig.suptitle("full pipeline: image-mean E vs Eq. 13 least squares", fontsize=10)
    return _save(fig, path)


def _terms_title(st: dict) -> str:
    return f"E_v {st['E_v']:.3f} E_s {st['E_s']:.3f} E_t {st['E_t']:.3f} S {st['S']:.3f}"


def shape_figure(path, exp: dict) -> Path:
    """Before/after images and v_s (top); delta_s before/after and v_i after (bottom)."""
    b, a = exp["before"], exp["after"]
    p = _panel(b["_images"]["image"])
    fig = _figure(3 * p + 1.2, 2 * (p + 0.45) + 0.4)
    axes = fig.subplots(2, 3)
    _show_image(axes[0, 0], b["_images"]["image"], f"before lighting (E_s {b['E_s']:.3f})")
    _show_image(axes[0, 1], a["_images"]["image"], f"after lighting (E_s {a['E_s']:.3f})")
    im = _show_map(
        axes[0, 2],
        b["_images"]["v_s"],
        b["_images"]["ds_mask"],
        "v_s: structural shape (curvature)",
        1.0,
        "magma",
    )
    fig.colorbar(im, ax=axes[0, 2], shrink=0.8, label="v_s")
    _show_map(axes[1, 0], b["_images"]["ds"], b["_images"]["ds_mask"], "δ_s before", 1.0)
    im = _show_map(axes[1, 1], a["_images"]["ds"], a["_images"]["ds_mask"], "δ_s after", 1.0)
    fig.colorbar(im, ax=axes[1, :2], shrink=0.8, label="δ_s (shape-measure image)")
    im = _show_map(
        axes[1, 2],
        a["_images"]["v_i"],
        a["_images"]["ds_mask"],
        "v_i after: image variation (log-luminance gradient)",
        1.0,
        "magma",
    )
    fig.colorbar(im, ax=axes[1, 2], shrink=0.8, label="v_i")
    fig.suptitle(f"{exp['dataset']}: shape enhancement (lighting stage)", fontsize=10)
    return _save(fig, path)


def saturation_figure(path, exp: dict) -> Path:
    """Draw the four renderings side by side and perceived transparency against saturation."""
    series = exp["series"]
    panels = []
    for p in series:
        t = p.get("outer_tap")
        shown = "undetermined" if t is None else f"{t:.3f}"
        title = f"saturation {p['saturation_percent']} %\nTAP transparency {shown}"
        panels.append((p["_images"]["image"], title))
    fig, ax = _images_over_plot(panels, 0.5)
    xs = [p["saturation_percent"] for p in series]
    names = list(series[0]["perceived_transparency"])
    for n in names:
        ys = [p["perceived_transparency"][n] for p in series]
        ys = [np.nan if y is None else y for y in ys]
        ax.plot(
            xs,
            ys,
            "o-" if n == exp["outer"] else "o--",
            label=n,
            linewidth=2 if n == exp["outer"] else 1,
        )
    plain = [p.get("outer_transparency_plain") for p in series]
    if any(v is not None for v in plain):  # the paper's plain-view reading of an encloser
        ys = [np.nan if v is None else v for v in plain]
        ax.plot(xs, ys, "^:", color="grey", label=f"{exp['outer']} (plain view)")
    taps = [np.nan if p.get("outer_tap") is None else p["outer_tap"] for p in series]
    ax.plot(xs, taps, "s-", color="black", linewidth=2, label=f"TAP {exp['outer']}")
    ax.set_xlabel(f"saturation of '{exp['outer']}' (%)", fontsize=8)
    ax.set_ylabel("perceived transparency (α_t; TAP)", fontsize=8)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.tick_params(labelsize=7)
    fig.suptitle(f"{exp['dataset']}: outer-layer saturation vs perceived transparency", fontsize=10)
    return _save(fig, path)


def pipeline_figure(path, exp: dict) -> Path:
    """Draw the four images (original, after each stage) with their terms, and the term plot."""
    steps = exp["steps"]
    panels = [
        (
            st["_images"]["image"],
            f"{st['label']}\nE_v {st['E_v']:.3f}  E_s {st['E_s']:.3f}  E_t {st['E_t']:.3f}",
        )
        for st in steps
    ]
    fig, ax = _images_over_plot(panels, 0.6)
    xs = np.arange(len(steps))
    for term, colour in (("E_v", "#4c72b0"), ("E_s", "#dd8452"), ("E_t", "#55a868")):
        ax.plot(xs, [s[term] for s in steps], "o-", color=colour, label=term)
    ax.set_xticks(xs, [s["label"].replace("after ", "+") for s in steps], fontsize=7)
    ax.set_ylabel("term (lower is better)", fontsize=8)
    ax.legend(fontsize=7)
    ax.tick_params(labelsize=7)
    fig.suptitle(f"{exp['dataset']}: full pipeline (opacity → lighting → colour)", fontsize=10)
    return _save(fig, path)


def performance_figure(path, perf: dict) -> Path:
    """Frame and optimisation time against image pixels and against volume voxels (log-log).

    One colour per volume; line style per quantity.
    """
    fig = _figure(10.0, 3.8)
    ax_img, ax_vol = fig.subplots(1, 2)
    colours = dict(
        zip(
            sorted({*perf["image_size"], *perf["volume_size"]}),
            ("#4c72b0", "#dd8452", "#55a868", "#c44e52"),
            strict=False,
        )
    )
    quantities = (
        ("frame_s", "o-", "our frame"),
        ("vtk_frame_s", "s:", "VTK CPU frame"),
        ("optimize_s", "d--", "whole optimisation"),
        ("curvature_s", "^-.", "curvature volume"),
    )
    for ax, sweep, xkey in ((ax_img, "image_size", "pixels"), (ax_vol, "volume_size", "voxels")):
        for name, points in perf[sweep].items():
            xs = [p["size"][0] * p["size"][1] if xkey == "pixels" else p["voxels"] for p in points]
            for key, style, label in quantities:
                ys = [p.get(key) for p in points]
                if all(y is not None for y in ys):
                    ax.plot(xs, ys, style, color=colours[name], label=f"{name}: {label}")
    for name, points in perf.get("full_resolution", {}).items():
        ax_img.plot(
            [p["size"][0] * p["size"][1] for p in points],
            [p["optimize_s"] for p in points],
            "x-",
            color=colours.get(name, "k"),
            label=f"{name}: whole optimisation, no image sampling",
        )
    for ax in (ax_img, ax_vol):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylabel("seconds", fontsize=8)
        ax.legend(fontsize=6)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="both", alpha=0.3)
    first = next(iter(perf["image_size"].values()))
    ax_img.set_xticks(
        [p["size"][0] * p["size"][1] for p in first], [f"{p['size'][0]}²" for p in first]
    )
    ax_img.minorticks_off()
    vol = next(iter(perf["volume_size"].values()))
    ax_vol.set_xticks([p["voxels"] for p in vol], ["×".join(map(str, p["dims"])) for p in vol])
    ax_vol.minorticks_off()
    ax_img.set_xlabel("image size", fontsize=8)
    ax_img.set_title("time vs image size (full volume)", fontsize=9)
    size = vol[0]["size"]
    ax_vol.set_xlabel(f"volume (every n-th voxel; image {size[0]}×{size[1]})", fontsize=8)
    ax_vol.set_title("time vs volume size", fontsize=9)
    return _save(fig, path)
