"""Where ``bench``'s ``measure_total_s`` goes: the analysis and each measure (issue 31, D5).

Run from a checkout, e.g.::

    NUMBA_NUM_THREADS=1 python -m benchmarks.measure_split --cpu --repeat 7

For each volume (default: the four 256^3 volumes of D5) at ``--size``, the default view and
structures of ``bench``, it times in turn, ``--repeat`` times: the measure's analysis
(:func:`~dvr_perception.rays.engine.analyze` without a cache), visibility, shape and
transparency one after the other on a fresh analysis (the luminance they share made first,
timed as ``luminance``), of transparency the walk of the enclosing layers' pixels without them
(D7, :func:`~dvr_perception.rays.engine.recomposites`), and
:func:`~dvr_perception.measures.all_measures` on another fresh analysis (transparency in its
worker thread).  It prints the medians per volume as one JSON line.  ``--cpu`` times the
process's CPU time (all threads) instead of the wall clock: with one numba thread on a loaded
machine it measures the work, not the neighbours.  ``all_measures`` with two threads cannot
beat ``(its CPU time at one thread) / 2``: the split shows which thread's share bounds it
(transparency, with the walk, runs beside visibility and shape).

Measured on the 2-core development machine (loaded; ``--cpu``, one thread, 512^2, seconds):
cthead analysis 0.229, luminance 0.006, visibility 0.008, shape 0.020, transparency 0.072
(its walk of the enclosers' pixels 0.050 of it), all_measures 0.110; engine 0.124 / 0.006 /
0.007 / 0.020 / 0.062 / 0.095; bonsai 0.202 / 0.005 / 0.006 / 0.022 / 0.010 (no walk) /
0.044; lobster 0.237 / 0.005 / 0.007 / 0.027 / 0.029 / 0.070.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time


def main(argv=None) -> int:
    """Time the measure's parts; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="../shared/data")
    p.add_argument("--volumes", default="cthead,engine,bonsai,lobster")
    p.add_argument("--size", default="512")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--cpu", action="store_true", help="process CPU time, not wall clock")
    args = p.parse_args(argv)

    from dvr_perception.cli import build_parser
    from dvr_perception.cli._common import load_inputs
    from dvr_perception.measures import all_measures
    from dvr_perception.measures.results import _accumulated, _image_luminance
    from dvr_perception.measures.shape import shape
    from dvr_perception.measures.transparency import transparency
    from dvr_perception.measures.visibility import visibility
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze, recomposites

    clock = time.process_time if args.cpu else time.perf_counter
    for name in args.volumes.split(","):
        cli = ["bench", f"{args.data}/{name}.nhdr", "--size", args.size]
        inputs = load_inputs(build_parser().parse_args(cli))
        vol, spec, cam = inputs.volume, inputs.spec, inputs.camera
        curv = curvature_source(vol, spec)

        def fresh(vol=vol, spec=spec, cam=cam, curv=curv):
            return analyze(vol, spec, cam, curvature=curv, build_cache=False)

        all_measures(fresh(), spec)  # compiles (or loads) every kernel
        times: dict[str, list[float]] = {}
        for _ in range(args.repeat):
            t0 = clock()
            analysis = fresh()
            t1 = clock()
            _image_luminance(analysis, spec, _accumulated(analysis).shape)
            t2 = clock()
            visibility(analysis, spec)
            t3 = clock()
            shape(analysis, spec)
            t4 = clock()
            transparency(analysis, spec)
            t5 = clock()
            walks = recomposites(analysis)
            again = fresh()
            t6 = clock()
            all_measures(again, spec)
            t7 = clock()
            parts = {
                "analysis": t1 - t0,
                "luminance": t2 - t1,
                "visibility": t3 - t2,
                "shape": t4 - t3,
                "transparency": t5 - t4,
                "rewalk_wall": sum(w["seconds"] for w in walks),
                "all_measures": t7 - t6,
            }
            for key, value in parts.items():
                times.setdefault(key, []).append(value)
        row = {key: round(statistics.median(v), 5) for key, v in times.items()}
        print(json.dumps({"volume": name, "cpu": args.cpu, **row}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
