"""``dvr-perception demo``: render the built-in phantom and write its outputs.

The demo is a list of *stages*; each takes the :class:`DemoState` and adds results and output
files to it: :func:`stage_render` renders the phantom with its own spec, :func:`stage_optimize`
runs ``dvr-perception optimize`` on it (all three stages) into the same folder and adds the
before/after terms to the summary.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dvr_perception._files import atomic_path, output_folder, write_png
from dvr_perception.cli._common import (
    coverage,
    emit_json,
    log,
    parse_size,
    save_buffers,
)

__all__ = ["DemoState", "add_parser", "run", "stage_optimize", "stage_render", "write_share_grid"]


def add_parser(subparsers, parents) -> None:
    """Register the ``demo`` sub-command."""
    p = subparsers.add_parser(
        "demo",
        parents=parents,
        help="render the built-in phantom, optimise it and write images, figures and specs",
        description="Render the phantom and write phantom.png, phantom_buffers.npz, "
        "phantom_spec.json and visible_share.png into --out; then optimise its opacity, "
        "lighting and colour and write the outputs of 'optimize' there too.",
    )
    p.add_argument("--out", default="demo_out", metavar="DIR", help="output folder (demo_out)")
    p.add_argument("--size", default="256", metavar="N|WxH", help="image size (default 256)")
    p.set_defaults(run=run)


@dataclass
class DemoState:
    """What the demo stages share: inputs, results, written files and timings."""

    out_dir: Path
    width: int
    height: int
    volume: object = None
    spec: object = None
    camera: object = None
    results: dict = field(default_factory=dict)
    files: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


def write_share_grid(path, shares, names, *, mask=None, title: str = "visible share") -> Path:
    """Write a grid of per-structure share images (values in [0, 1]) as a PNG, atomically.

    Each panel is titled with the mean share over ``mask`` (default: all pixels).
    """
    from matplotlib.figure import Figure

    from dvr_perception.cli._plots import plot_text

    shares = np.asarray(shares, float)
    k = shares.shape[0]
    mask = np.ones(shares.shape[1:], bool) if mask is None else np.asarray(mask, bool)
    cols = min(k, 4)
    rows = -(-k // cols)
    fig = Figure(figsize=(3.0 * cols, 3.0 * rows + 0.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    im = None
    for i, ax in enumerate(axes):
        ax.set_axis_off()
        if i < k:
            im = ax.imshow(shares[i], vmin=0.0, vmax=1.0, cmap="magma", interpolation="nearest")
            mean = float(shares[i][mask].mean()) if mask.any() else 0.0
            ax.set_title(f"{plot_text(names[i])} (mean {mean:.3f})", fontsize=9)
    fig.suptitle(title)
    if im is not None:
        fig.colorbar(im, ax=list(axes), shrink=0.8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    return Path(path)


def stage_render(state: DemoState) -> None:
    """Render the phantom with its own spec and write image, buffers, spec and share grid."""
    from dvr_perception.rays.camera import Camera
    from dvr_perception.rays.engine import analyze
    from dvr_perception.structures.io import save_spec
    from dvr_perception.structures.phantom import make_phantom

    t0 = time.perf_counter()
    state.volume, state.spec = make_phantom()
    az, el, zoom = state.spec.view or (0.0, 0.0, 1.0)
    state.camera = Camera.from_view(
        state.volume.bounds,
        azimuth=az,
        elevation=el,
        zoom=zoom,
        width=state.width,
        height=state.height,
    )
    state.seconds["phantom"] = time.perf_counter() - t0
    log.info("rendering the phantom at %dx%d", state.width, state.height)
    t0 = time.perf_counter()
    result = analyze(state.volume, state.spec, state.camera, build_cache=False)
    state.seconds["render"] = time.perf_counter() - t0
    state.results["initial"] = result
    d = state.out_dir
    state.files.append(write_png(d / "phantom.png", result.image))
    state.files.append(save_buffers(d / "phantom_buffers.npz", result))
    save_spec(state.spec, d / "phantom_spec.json")
    state.files.append(d / "phantom_spec.json")
    shares = np.asarray(result.visible_share)
    covered = np.asarray(result.accumulated) > 0
    title = "visible share (visible / accumulated opacity); means over covered pixels"
    grid = write_share_grid(
        d / "visible_share.png", shares, result.names, mask=covered, title=title
    )
    state.files.append(grid)
    state.summary["structures"] = list(result.names)
    state.summary["coverage"] = coverage(result)
    state.summary["visible_share_mean"] = {
        n: float(shares[i][covered].mean()) if covered.any() else 0.0
        for i, n in enumerate(result.names)
    }


def stage_optimize(state: DemoState) -> None:
    """Optimise the phantom's spec (``dvr-perception optimize``) and write its outputs."""
    from dvr_perception.cli.optimize import Progress, optimize_and_report, stop_on_interrupt

    t0 = time.perf_counter()
    stages = ("opacity", "lighting", "colour")
    progress = Progress(len(stages) * 10)
    with stop_on_interrupt(progress):
        report = optimize_and_report(
            state.volume, state.spec, state.camera, state.out_dir, stages=stages,
            progress=progress,
        )  # fmt: skip
    state.seconds["optimize"] = time.perf_counter() - t0
    state.files.extend(Path(f) for f in report["files"])
    keys = ("E_v", "E_s", "E_t", "E")
    state.summary["optimize"] = {
        "initial": {k: report["initial"][k] for k in keys},
        "final": {k: report["final"][k] for k in keys},
        "status": report["status"],
        "message": report["message"],
        "why": [e["line"] for e in report["structures"].values()],
    }


STAGES = [stage_render, stage_optimize]


def run(args: argparse.Namespace) -> int:
    """Execute ``demo``."""
    from dvr_perception.rays import memory
    from dvr_perception.volume.phantom import PHANTOM_MATERIALS

    w, h = parse_size(args.size)
    memory.check_image(w, h, len(PHANTOM_MATERIALS))  # before the folder is made
    with output_folder(args.out) as staged:  # checked and locked before the work
        state = DemoState(out_dir=staged.path, width=w, height=h)
        t0 = time.perf_counter()
        for stage in STAGES:
            stage(state)
        state.seconds["total"] = time.perf_counter() - t0
        report = {
            **state.summary,
            "size": [w, h],
            "out_dir": str(staged.final),
            "files": [str(staged.final_path(f)) for f in state.files],
            "seconds": state.seconds,
        }
        report = staged.relocate(report)
    state.out_dir = staged.final
    if args.json:
        emit_json(report)
        return 0
    print(f"phantom demo ({w}x{h}) -> {state.out_dir}/")
    print(f"  structures: {', '.join(report['structures'])}")
    print(f"  accumulated coverage: {report['coverage']:.1%} of pixels")
    for name, share in report["visible_share_mean"].items():
        print(f"  mean visible share of {name} (covered pixels): {share:.3f}")
    opt = report.get("optimize")
    if opt is not None:
        a, b = opt["initial"], opt["final"]
        print("  optimised (opacity, lighting, colour): before -> after")
        for k in ("E_v", "E_s", "E_t", "E"):
            print(f"    {k:<3} {a[k]:.4f} -> {b[k]:.4f}")
        for line in opt["why"]:
            print(f"    {line}")
        print(f"    status {opt['status']}: {opt['message']}")
    times = ", ".join(f"{k} {v:.2f}" for k, v in state.seconds.items() if k != "phantom")
    print(f"  seconds: {times}")
    for f in report["files"]:
        print(f"  wrote {f}")
    return 0
