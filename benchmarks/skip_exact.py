"""The skipping walk behind early ray termination against the exact walk (D8): ``skip_exact.json``.

Run as ``python -m benchmarks.skip_exact --data ../shared/data --out
benchmarks/skip_exact.json [--volumes engine,cthead] [--size 256]``.  Every volume with a
preset in ``state_files/`` is read with that preset and analysed without the re-evaluation
cache (what ``dvr-perception measure`` does) from three views (azimuth 0, 120 and 240 degrees
at 20 degrees of elevation), once with the skipping walk (the default) and once with
``exact=True``.  Per view: the largest ``|ΔE|`` of each term (``E_v``, ``E_s``, ``E_t``; they
must agree within 1e-6), whether every buffer the measures read is the exact walk's
(``assigned`` as ``min(assigned, 1)``), the samples each walk visited and the faster of two
timings of each analysis.  The readings that take ``assigned`` beyond saturation need the
exact walk: ``visibility(..., composition="thickness")`` refuses a skipping analysis, and the
difference the skipping walk makes in the image-wide ``assigned_share`` (that of the capped
opacities) is recorded.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VIEWS = ((0.0, 20.0), (120.0, 20.0), (240.0, 20.0))
#: What the measures read, equal to the bit between the two walks.
SAME = ("rgba", "image", "accumulated", "visible", "present", "curvature",
        "importance_accumulated")  # fmt: skip


def _scene(data: Path, name: str):
    from dvr_perception.structures.io import attach_labels, load_spec
    from dvr_perception.volume.io import load_volume

    volume = load_volume(data / f"{name}.nhdr")
    spec = load_spec(REPO / "state_files" / f"{name}.json")
    return attach_labels(volume, spec), spec


def _timed(fn, repeat: int = 2):
    """Return ``(result, fastest seconds)`` of ``repeat`` calls."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def _terms(analysis, spec) -> dict:
    from dvr_perception.measures import all_measures

    m = all_measures(analysis, spec)
    return {
        "E_v": m.visibility.E_v,
        "E_s": m.shape.E_s,
        "E_t": m.transparency.E_t,
        "assigned_share": {n: v["assigned_share"] for n, v in m.visibility.per_structure.items()},
    }


def measure_volume(data: Path, name: str, size: int, log) -> dict:
    """Return ``{"views": [...], "max_dE": {term: max over views}, walked and time totals}``."""
    import numpy as np

    from dvr_perception.rays import Camera
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze

    volume, spec = _scene(data, name)
    curvature = curvature_source(volume, spec)
    views = []
    for azimuth, elevation in VIEWS:
        cam = Camera.from_view(volume.bounds, azimuth=azimuth, elevation=elevation,
                               width=size, height=size)  # fmt: skip

        def run(exact, cam=cam):
            return analyze(volume, spec, cam, curvature=curvature, build_cache=False, exact=exact)

        run(False)  # the first analysis of a volume makes its derived volumes: not timed
        skip, t_skip = _timed(lambda run=run: run(False))
        exact, t_exact = _timed(lambda run=run: run(True))
        same = {f: bool(np.array_equal(getattr(skip, f), getattr(exact, f))) for f in SAME}
        same["assigned"] = bool(np.array_equal(skip.assigned, np.minimum(exact.assigned, 1.0)))
        ts, te = _terms(skip, spec), _terms(exact, spec)
        row = {
            "azimuth": azimuth,
            "elevation": elevation,
            "dE": {t: abs(ts[t] - te[t]) for t in ("E_v", "E_s", "E_t")},
            "E_exact": {t: te[t] for t in ("E_v", "E_s", "E_t")},
            "buffers_equal": same,
            "samples": int(exact.stats["samples"]),
            "samples_walked_exact": int(exact.stats["samples_walked"]),
            "samples_walked_skipping": int(skip.stats["samples_walked"]),
            "analyze_exact_s": t_exact,
            "analyze_skipping_s": t_skip,
            "max_d_assigned_share": max(
                abs(ts["assigned_share"][n] - te["assigned_share"][n]) for n in te["assigned_share"]
            ),
        }
        views.append(row)
        log(f"{name} az {azimuth:g}: max|dE| {max(row['dE'].values()):.2e}, walked "
            f"{row['samples_walked_skipping']}/{row['samples_walked_exact']} "
            f"({row['samples_walked_skipping'] / max(row['samples_walked_exact'], 1):.2f}), "
            f"analyze {t_skip:.3f}/{t_exact:.3f} s, buffers "
            f"{'equal' if all(same.values()) else same}")  # fmt: skip
    walked_e = sum(v["samples_walked_exact"] for v in views)
    walked_s = sum(v["samples_walked_skipping"] for v in views)
    return {
        "dims": list(volume.dims),
        "views": views,
        "max_dE": {t: max(v["dE"][t] for v in views) for t in ("E_v", "E_s", "E_t")},
        "buffers_equal": all(all(v["buffers_equal"].values()) for v in views),
        "walked_ratio": walked_s / max(walked_e, 1),
        "time_ratio": sum(v["analyze_skipping_s"] for v in views)
        / max(sum(v["analyze_exact_s"] for v in views), 1e-12),
    }


def main(argv=None) -> int:
    """Measure the volumes named (default: every preset with shared data) and write JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    p.add_argument("--out", default=str(REPO / "benchmarks" / "skip_exact.json"))
    p.add_argument("--volumes", default=None, help="comma-separated names (default: all)")
    p.add_argument("--size", type=int, default=256)
    args = p.parse_args(argv)
    data = Path(args.data)
    if args.volumes:
        names = args.volumes.split(",")
    else:
        names = sorted(f.stem for f in (REPO / "state_files").glob("*.json")
                       if (data / f"{f.stem}.nhdr").is_file())  # fmt: skip

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    import numba

    out = {"size": args.size, "views": [list(v) for v in VIEWS],
           "numba_threads": int(numba.get_num_threads()), "volumes": {}}  # fmt: skip
    for name in names:
        out["volumes"][name] = measure_volume(data, name, args.size, log)
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    vols = out["volumes"].values()
    out["max_dE"] = {t: max(v["max_dE"][t] for v in vols) for t in ("E_v", "E_s", "E_t")}
    out["buffers_equal"] = all(v["buffers_equal"] for v in vols)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    log(f"{len(out['volumes'])} volumes x {len(VIEWS)} views at {args.size} px: max |dE| "
        + ", ".join(f"{t} {d:.2e}" for t, d in out["max_dE"].items())
        + f"; every buffer the measures read equal: {out['buffers_equal']}")  # fmt: skip
    for name, v in out["volumes"].items():
        log(f"  {name:16s} walked {v['walked_ratio']:.2f} of the exact walk's samples, "
            f"analysis time {v['time_ratio']:.2f}x")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
