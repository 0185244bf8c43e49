"""``dvr-perception render``: render a volume with our engine and write the image and buffers."""

from __future__ import annotations

import argparse
import time

from dvr_perception._files import check_distinct, staged_files, write_png
from dvr_perception.cli._backend import add_backend_arg
from dvr_perception.cli._common import (
    add_input_args,
    check_output_file,
    coverage,
    emit_json,
    load_inputs,
    log,
    save_buffers,
)

__all__ = ["add_parser", "run"]

EXAMPLE = """examples:
  dvr-perception render phantom --size 256 --out phantom.png
  dvr-perception render ../shared/data/engine.nhdr --view=30,20 --out engine.png \\
      --buffers engine.npz --json
"""


def add_parser(subparsers, parents) -> None:
    """Register the ``render`` sub-command."""
    p = subparsers.add_parser(
        "render",
        parents=parents,
        help="render a volume to a PNG (and optionally its per-pixel buffers)",
        description="Render VOLUME with the ray-analysis engine.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_args(p)
    p.add_argument("--out", required=True, metavar="IMG.png", help="output image")
    add_backend_arg(p)
    p.add_argument(
        "--buffers",
        metavar="OUT.npz",
        help="also write rgba, image, accumulated, visible, assigned, shares, present, "
        "curvature, names and camera JSON",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Execute ``render``."""
    check_distinct({"--out": args.out, "--buffers": args.buffers})
    out = check_output_file(args.out)
    buffers = check_output_file(args.buffers) if args.buffers else None
    inputs = load_inputs(args)
    from dvr_perception.rays.engine import analyze

    log.info("rendering %dx%d", inputs.camera.width, inputs.camera.height)
    t0 = time.perf_counter()
    curvature = None
    if buffers is not None:  # the curvature buffer needs the curvature volume (~2 s at 256^3)
        from dvr_perception.rays.curvature_field import curvature_source

        curvature = curvature_source(inputs.volume, inputs.spec)
    # the image alone needs no sample behind early ray termination; the buffers' assigned
    # (occlusion-free) opacities need every sample of every ray (exact: not capped where
    # presence saturates, as the measures alone would allow)
    result = analyze(
        inputs.volume, inputs.spec, inputs.camera, curvature=curvature, build_cache=False,
        occlusion_free=buffers is not None, backend=args.backend, exact=True,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    with staged_files(*([out] if buffers is None else [out, buffers])) as tmps:
        write_png(tmps[0], result.image)  # both files appear together, or neither
        if buffers is not None:
            save_buffers(tmps[1], result)
    summary = {
        "out": str(out),
        "buffers": str(buffers) if buffers is not None else None,
        "volume": inputs.volume_source,
        "spec": inputs.spec_source,
        "size": [inputs.camera.width, inputs.camera.height],
        "structures": list(result.names),
        "coverage": coverage(result),
        "seconds": seconds,
        "camera": inputs.camera.to_dict(),
    }
    if args.json:
        emit_json(summary)
    else:
        print(f"wrote {out} ({inputs.camera.width}x{inputs.camera.height}, {seconds:.2f} s)")
        if buffers is not None:
            print(f"wrote {buffers}")
    return 0
