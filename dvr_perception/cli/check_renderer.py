"""``dvr-perception check-renderer``: compare our engine's image with VTK's volume mappers.

Writes ``<name>_ours.png``, ``<name>_vtk_<mapper>.png`` and ``<name>_diff_<mapper>.png`` (the
absolute difference, amplified 4x) into ``--out-dir`` and reports SSIM and mean absolute
difference per mapper.  ``--against plotter`` compares with our PyVista display instead
(:func:`dvr_perception.plotting.render_plotter`, per-structure lighting; same JSON keys, with
``mapper: "plotter"`` and the screenshot in ``vtk_png``).  With ``--mapper all`` a mapper
that fails (typically the GPU mapper without a usable OpenGL driver) is reported as an entry
with ``error`` instead of aborting.
``seconds_ours`` is one cold :func:`~dvr_perception.rays.engine.analyze` call (loading the
numba kernels included) and ``seconds_vtk`` one warm VTK frame; use ``bench`` for timings.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from dvr_perception._files import output_folder, write_png
from dvr_perception.cli._common import (
    add_input_args,
    emit_json,
    load_inputs,
    log,
)

__all__ = ["add_parser", "run"]

MAPPERS = ("fixed_point", "gpu")
AGAINST = ("vtk", "plotter")
DIFF_GAIN = 4.0
EXAMPLE = """examples:
  dvr-perception check-renderer phantom --size 96 --json
  dvr-perception check-renderer ../shared/data/engine.nhdr --mapper all --out-dir check
  dvr-perception check-renderer phantom --size 96 --against plotter --json
"""


def add_parser(subparsers, parents) -> None:
    """Register the ``check-renderer`` sub-command."""
    p = subparsers.add_parser(
        "check-renderer",
        parents=parents,
        help="compare our rendering with VTK's (SSIM, mean absolute difference)",
        description="Render VOLUME with our engine and with VTK, and compare the images.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_args(p)
    p.add_argument(
        "--mapper",
        choices=(*MAPPERS, "all"),
        default="fixed_point",
        help="VTK mapper to compare with (default fixed_point, the CPU ray caster)",
    )
    p.add_argument(
        "--against",
        choices=AGAINST,
        default="vtk",
        help="compare with VTK's mappers (default) or with our PyVista plotter display",
    )
    p.add_argument(
        "--out-dir",
        default="bench_out/check_renderer",
        metavar="DIR",
        help="where the PNGs go (default bench_out/check_renderer)",
    )
    p.set_defaults(run=run)


def _stem(source: str) -> str:
    return "phantom" if source == "phantom" else Path(source).name.split(".")[0]


def _render_plotter(inputs):
    from dvr_perception.plotting import render_plotter

    t0 = time.perf_counter()
    image = render_plotter(inputs.volume, inputs.spec, inputs.camera)
    return image, "plotter", time.perf_counter() - t0


def _compare_one(inputs, ours_image, mapper: str, out_dir: Path, stem: str) -> dict:
    from dvr_perception.rays.vtk_reference import compare_images, render_vtk

    if mapper == "plotter":
        log.info("rendering through the PyVista plotter")
        image, name, seconds = _render_plotter(inputs)
    else:
        log.info("rendering with VTK (%s)", mapper)
        ref = render_vtk(inputs.volume, inputs.spec, inputs.camera, mapper=mapper)
        image, name, seconds = ref.image, ref.mapper, ref.seconds
    scores = compare_images(ours_image, image)
    vtk_png = write_png(out_dir / f"{stem}_vtk_{mapper}.png", image)
    diff = np.clip(np.abs(np.asarray(ours_image, float) - image) * DIFF_GAIN, 0.0, 1.0)
    diff_png = write_png(out_dir / f"{stem}_diff_{mapper}.png", diff)
    return {
        "mapper": name,
        "ssim": float(scores["ssim"]),
        "mean_abs_diff": float(scores["mean_abs_diff"]),
        "vtk_png": str(vtk_png),
        "diff_png": str(diff_png),
        "seconds_vtk": float(seconds),
    }


def run(args: argparse.Namespace) -> int:
    """Execute ``check-renderer``."""
    inputs = load_inputs(args)
    with output_folder(args.out_dir) as staged:  # checked and locked before the work
        report = _check(args, inputs, staged.path)
        report = staged.relocate(report)
    ours_png, seconds_ours = report["ours_png"], report["seconds_ours"]
    if args.json:
        emit_json(report)
    else:
        print(f"ours: {ours_png} ({seconds_ours:.2f} s)")
        for e in report.get("mappers", [report]):
            if "error" in e:
                print(f"{e['mapper']}: error: {e['error']}")
            else:
                print(
                    f"{e['mapper']}: ssim {e['ssim']:.4f}, mean |diff| {e['mean_abs_diff']:.4f}, "
                    f"{e['seconds_vtk']:.2f} s -> {e['vtk_png']}"
                )
    return 0


def _check(args, inputs, out_dir: Path) -> dict:
    from dvr_perception.rays.engine import analyze

    t0 = time.perf_counter()
    result = analyze(inputs.volume, inputs.spec, inputs.camera, build_cache=False)
    seconds_ours = time.perf_counter() - t0
    stem = _stem(inputs.volume_source)
    ours_png = write_png(out_dir / f"{stem}_ours.png", result.image)
    base = {
        "volume": inputs.volume_source,
        "spec": inputs.spec_source,
        "size": [inputs.camera.width, inputs.camera.height],
        "ours_png": str(ours_png),
        "seconds_ours": seconds_ours,
    }
    if args.against == "plotter":
        report = {**base, **_compare_one(inputs, result.image, "plotter", out_dir, stem)}
    elif args.mapper == "all":
        entries = []
        for mapper in MAPPERS:
            try:
                entries.append(_compare_one(inputs, result.image, mapper, out_dir, stem))
            except Exception as exc:  # a broken mapper is a finding, not a crash
                msg = " ".join(f"{type(exc).__name__}: {exc}".split())
                log.warning("VTK %s mapper failed: %s", mapper, msg)
                entries.append({"mapper": mapper, "error": msg})
        report = {**base, "mapper": "all", "mappers": entries}
    else:
        report = {**base, **_compare_one(inputs, result.image, args.mapper, out_dir, stem)}
    return report
