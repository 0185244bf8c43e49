"""Bricked against whole-volume analysis of one volume, in one process (issue 31).

Run from a checkout, e.g.::

    NUMBA_NUM_THREADS=1 python -m benchmarks.bricked_vs_whole --cpu --repeat 5

analyses cthead up-sampled to 512 x 512 x 452 (``--resample 2,2,4``) at 512^2 whole and in
bricks of 256^3 cells (``--brick``), alternating, for the render (no cache, stops at early ray
termination), the measure's analysis (occlusion-free, no cache) and the frame (with the cache),
and prints per kind the median seconds of each way, their ratio and the largest difference of
the buffers (0: bit-equal).  ``--cpu`` times the process's CPU time instead of the wall clock:
on a loaded machine with one numba thread it measures the work, not the neighbours.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main(argv=None) -> int:
    """Time whole against bricked analyses; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--volume", default="../shared/data/cthead.nhdr")
    p.add_argument("--resample", default="2,2,4")
    p.add_argument("--size", default="512")
    p.add_argument("--brick", default="256,256,256", help="cells per brick z,y,x")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--cpu", action="store_true", help="process CPU time, not wall clock")
    args = p.parse_args(argv)

    from dvr_perception.cli import build_parser
    from dvr_perception.inputs import load_inputs
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze

    cli = ["bench", args.volume, "--preset", "cthead", "--size", args.size]
    if args.resample:
        cli += ["--resample", args.resample]
    scene = load_inputs(build_parser().parse_args(cli))
    vol, spec, cam = scene.volume, scene.spec, scene.camera
    curv = curvature_source(vol, spec, memory_limit="16G")
    brick = tuple(int(v) for v in args.brick.split(","))
    kinds = {
        "render": {"build_cache": False, "occlusion_free": False},
        "measure": {"curvature": curv, "build_cache": False},
        "frame": {"curvature": curv, "build_cache": True},
    }
    clock = time.process_time if args.cpu else time.perf_counter

    def timed(kw, **extra):
        t0 = clock()
        res = analyze(vol, spec, cam, memory_limit="16G", **kw, **extra)
        return clock() - t0, res

    print(f"numba threads {os.environ.get('NUMBA_NUM_THREADS', 'default')}, "
          f"{'cpu' if args.cpu else 'wall'} seconds, bricks {brick}")  # fmt: skip
    for name, kw in kinds.items():
        _, a = timed(kw)
        _, b = timed(kw, brick=brick)  # (both warm: compiled, memos made)
        diff = max(
            float(np.abs(np.asarray(getattr(a, f), float) - np.asarray(getattr(b, f), float)).max())
            for f in ("rgba", "visible", "assigned", "curvature")
            if getattr(a, f, None) is not None
        )
        del a, b
        whole, parts = [], []
        for _ in range(args.repeat):
            whole.append(timed(kw)[0])
            parts.append(timed(kw, brick=brick)[0])
        w, q = float(np.median(whole)), float(np.median(parts))
        print(f"{name}: whole {w:.3f} s, bricked {q:.3f} s, ratio {q / w:.2f}, "
              f"max difference {diff:.1e}", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
