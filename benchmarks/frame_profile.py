"""Where a full frame's time and memory go: per-stage timers, resident memory and a profile.

Run from a checkout (issue 31), e.g.::

    python -m benchmarks.frame_profile --data ../shared/data --resample 2,2,4 --size 512

prints one JSON object: per stage (load, curvature, the analyses and each measure) the
median seconds and the resident memory after it and at its peak (``VmRSS``/``VmHWM``, the
peak reset before each stage where Linux allows it), the E terms, and with ``--profile N``
the ``N`` costliest functions of one full frame plus its measures (cProfile, cumulative).
``--save`` / ``--check`` write / compare the E terms and the analysis's fields (npz).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import json
import pstats
import sys
import time
from pathlib import Path

import numpy as np


def _status() -> dict:
    out = {}
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(("VmRSS", "VmHWM")):
                name, value = line.split(":")
                out[name] = int(value.split()[0]) / 1024  # MiB
    except OSError:
        pass
    return out


def _reset_peak() -> None:
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def main(argv=None) -> int:
    """Time and profile one frame; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="../shared/data", help="shared data folder")
    p.add_argument("--volume", default="cthead.nhdr")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--resample", default="2,2,4")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--profile", type=int, default=0, help="print the N costliest functions")
    p.add_argument("--save", help="write E terms and fields to this npz")
    p.add_argument("--check", help="compare E terms and fields with this npz")
    p.add_argument("--only", default="", help="comma list of stages to time (default all)")
    args = p.parse_args(argv)

    from benchmarks.cuda_check import _load, _median

    out: dict = {"stages": {}}

    def stage(name, fn, repeat=1):
        _reset_peak()
        t = _median(fn, repeat)
        st = _status()
        out["stages"][name] = {"s": round(t, 4), "rss_mb": st.get("VmRSS"),
                               "peak_mb": st.get("VmHWM")}  # fmt: skip
        print(name, json.dumps(out["stages"][name]), file=sys.stderr, flush=True)

    held = {}
    stage("load", lambda: held.update(scene=_load(Path(args.data) / args.volume, args.size,
                                                   args.resample or None)))  # fmt: skip
    scene = held["scene"]
    vol, spec, cam = scene.volume, scene.spec, scene.camera
    from dvr_perception.measures import all_measures
    from dvr_perception.measures.shape import shape
    from dvr_perception.measures.transparency import transparency
    from dvr_perception.measures.visibility import visibility
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze

    stage("curvature", lambda: held.update(curv=curvature_source(vol, spec)))
    curv = held["curv"]
    stage("warm_frame", lambda: held.update(a=analyze(vol, spec, cam, curvature=curv)))
    stage("warm_render", lambda: analyze(vol, spec, cam, build_cache=False, occlusion_free=False))
    stage("warm_measures", lambda: all_measures(held["a"], spec))
    ref = held.pop("a")
    terms = all_measures(ref, spec)
    out["terms"] = {"E_v": terms.visibility.E_v, "E_s": terms.shape.E_s,
                    "E_t": terms.transparency.E_t}  # fmt: skip
    fields = {f: np.asarray(getattr(ref, f)) for f in
              ("image", "visible", "assigned", "present", "curvature", "accumulated")}  # fmt: skip
    del ref, terms
    only = set(args.only.split(",")) if args.only else None

    def want(name):
        return only is None or name in only

    r = args.repeat
    if want("frame"):
        stage("frame", lambda: analyze(vol, spec, cam, curvature=curv), r)
    if want("render"):
        stage("render", lambda: analyze(vol, spec, cam, build_cache=False, occlusion_free=False),
              r)  # fmt: skip
    if want("measure_analysis"):
        stage("measure_analysis",
              lambda: analyze(vol, spec, cam, curvature=curv, build_cache=False), r)  # fmt: skip
    if want("measures"):
        for name, fn in (("visibility", lambda a: visibility(a, spec)),
                         ("shape", lambda a: shape(a, spec)),
                         ("transparency", lambda a: transparency(a, spec)),
                         ("all_measures", lambda a: all_measures(a, spec)),
                         ("all_measures_cached", lambda a: all_measures(a, spec))):  # fmt: skip
            times = []
            for _ in range(r):
                a = analyze(vol, spec, cam, curvature=curv, build_cache=name.endswith("cached"))
                t0 = time.perf_counter()
                fn(a)
                times.append(time.perf_counter() - t0)
                del a
            out["stages"][name] = {"s": round(float(np.median(times)), 4)}
            print(name, out["stages"][name], file=sys.stderr, flush=True)
    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        a = analyze(vol, spec, cam, curvature=curv, build_cache=False)
        all_measures(a, spec, parallel=False)
        prof.disable()
        del a
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(args.profile)
        print(s.getvalue(), file=sys.stderr)
    out["peak_rss_mb"] = _status().get("VmHWM")
    if args.save:
        np.savez(args.save, **fields, terms=json.dumps(out["terms"]))
    if args.check:
        old = np.load(args.check)
        t_old = json.loads(str(old["terms"]))
        out["terms_diff"] = {k: abs(out["terms"][k] - t_old[k]) for k in t_old}
        out["fields_diff"] = {
            f: float(np.nanmax(np.abs(fields[f].astype(float) - old[f].astype(float))))
            for f in fields
        }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
