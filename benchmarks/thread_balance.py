"""How evenly the walk's parallel chunks share the work among threads (issue 31, cores).

numba runs a ``prange`` over the 64 ray chunks of :func:`~dvr_perception.rays.engine.
ray_order` as equal runs of consecutive chunks, one run per thread (a static schedule); with
more than 4 threads the tiles are dealt to the chunks along the golden-ratio sequence, with
fewer round-robin.  The
time of a parallel walk is then that of the thread with the most work.  This script takes
each ray's walked samples (the work of the walk) from one analysis of cthead (up-sampled by
``--resample``) and prints, per analysis kind (``render``, ``measure``, ``frame``) and thread
count, the ideal speedup ``total work / largest run's work``, for the dealing in use and for
the former round-robin dealing.  No many-core machine is needed: on 16 cores the former
dealing measured 1.005 / 0.458 / 0.287 / 0.286 / 0.175 s (``frame``, 1 / 2 / 4 / 8 / 16
threads), the speedups 2.2 / 3.5 / 3.5 / 5.7 this model gives as 2.0 / 3.3 / 3.4 / 5.7.

Run from a checkout, e.g.::

    python -m benchmarks.thread_balance --data ../shared/data --resample 2,2,4 --size 512
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def _round_robin(height: int, width: int, tile=(16, 16), nchunk: int = 64):
    """Deal as before: tile ``i`` (row-major) to chunk ``i % nchunk``."""
    th, tw = tile
    rows = np.arange(height * width, dtype=np.int64).reshape(height, width)
    ty, tx = -(-height // th), -(-width // tw)
    tiles = [rows[y * th : (y + 1) * th, x * tw : (x + 1) * tw].ravel()
             for y in range(ty) for x in range(tx)]  # fmt: skip
    n = max(min(len(tiles), nchunk), 1)
    parts = [np.concatenate(tiles[c::n]) for c in range(n)]
    ptr = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    return np.concatenate(parts), ptr


def speedups(cost: np.ndarray, order: np.ndarray, chunk_ptr: np.ndarray, threads) -> dict:
    """Ideal speedup per thread count under numba's static schedule of the chunks."""
    per = np.add.reduceat(cost[order], chunk_ptr[:-1])
    n = len(per)
    out = {}
    for t in threads:
        runs = [per[i * n // t : (i + 1) * n // t].sum() for i in range(t)]
        out[t] = round(float(per.sum() / max(runs)), 2)
    return out


def _scratch() -> dict:
    """Return the engine's reused per-ray work arrays (the walk counts samples there)."""
    from dvr_perception.rays import engine

    found = getattr(engine, "_SCRATCH", None)
    if found is None:  # moved below the engine
        from dvr_perception.rays import _walk_setup

        found = _walk_setup._SCRATCH
    return found


def main(argv=None) -> int:
    """Print the balance figures; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="../shared/data", help="shared data folder")
    p.add_argument("--size", type=int, default=512, help="image size (default 512)")
    p.add_argument("--resample", default="2,2,4", help="cthead's up-sampling (default 2,2,4)")
    p.add_argument("--threads", default="1,2,4,8,16,32,64", help="thread counts")
    args = p.parse_args(argv)

    from benchmarks.cuda_check import _load
    from dvr_perception.rays import engine
    from dvr_perception.rays.curvature_field import curvature_source

    inputs = _load(Path(args.data) / "cthead.nhdr", args.size, args.resample or None)
    vol, spec, cam = inputs.volume, inputs.spec, inputs.camera
    curv = curvature_source(vol, spec)
    threads = [int(t) for t in args.threads.split(",")]
    nrays = cam.width * cam.height
    kinds = {
        "render": {"build_cache": False, "occlusion_free": False},
        "measure": {"curvature": curv, "build_cache": False},
        "frame": {"curvature": curv},
    }
    out = {"dims": list(vol.dims), "size": [cam.width, cam.height], "kinds": {}}
    for name, kw in kinds.items():
        engine.analyze(vol, spec, cam, backend="numba", **kw)
        cost = np.array(_scratch()["walked"][:nrays], np.float64)  # per-ray samples
        from dvr_perception.rays import _walk_setup

        many = _walk_setup._threads
        _walk_setup._threads = lambda: 64  # the dealing of many threads, whatever runs here
        try:
            golden = _walk_setup.ray_order(cam.height, cam.width)
        finally:
            _walk_setup._threads = many
        out["kinds"][name] = {
            "golden": speedups(cost, *golden, threads),
            "round_robin": speedups(cost, *_round_robin(cam.height, cam.width), threads),
        }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
