"""Thread scaling of the CPU engine (numba): one analysis at 1..N threads (issue 31).

Run from a checkout (VTK is not needed), e.g. on a 16-core machine::

    python -m benchmarks.thread_scaling --data ../shared/data --resample 2,2,4 --size 512

prints one JSON object: the volume's dims, the image size, numba's thread count, and per thread
count the median seconds of two analyses of cthead (up-sampled by ``--resample``) with the
curvature volume: ``frame`` (with the re-evaluation cache, as the optimiser's first pass),
``measure`` (no cache) and ``render`` (no cache, rays stop at early termination).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    """Time the analyses; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="../shared/data", help="shared data folder")
    p.add_argument("--size", type=int, default=512, help="image size (default 512)")
    p.add_argument("--resample", default="2,2,4", help="cthead's up-sampling (default 2,2,4)")
    p.add_argument("--threads", default="1,2,4,8,16", help="thread counts (default 1,2,4,8,16)")
    p.add_argument("--out", help="also write the JSON here")
    args = p.parse_args(argv)

    import numba

    from benchmarks.cuda_check import _load, _median
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze

    t0 = time.perf_counter()
    scene = _load(Path(args.data) / "cthead.nhdr", args.size, args.resample or None)
    curv = curvature_source(scene.volume, scene.spec)
    vol, spec, cam = scene.volume, scene.spec, scene.camera
    out = {"dims": list(vol.dims), "size": [cam.width, cam.height],
           "prepare_s": time.perf_counter() - t0,
           "max_threads": int(numba.config.NUMBA_NUM_THREADS), "threads": {}}  # fmt: skip
    analyze(vol, spec, cam, curvature=curv, backend="numba")  # compile / warm

    def run(**kw):
        return lambda: analyze(vol, spec, cam, backend="numba", **kw)

    for t in (int(x) for x in args.threads.split(",")):
        if t > numba.config.NUMBA_NUM_THREADS:
            continue
        numba.set_num_threads(t)
        out["threads"][t] = {
            "frame": _median(run(curvature=curv), 2),
            "measure": _median(run(curvature=curv, build_cache=False), 2),
            "render": _median(run(build_cache=False, occlusion_free=False), 2),
        }
        print(t, json.dumps(out["threads"][t]), file=sys.stderr, flush=True)
    text = json.dumps(out, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
