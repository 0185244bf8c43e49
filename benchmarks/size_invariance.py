"""E_s and E_t at several image sizes, same views (decision D9): ``size_invariance.json``.

Run as ``python -m benchmarks.size_invariance --data ../shared/data --out
benchmarks/size_invariance.json [--volumes engine,cthead] [--sizes 96,128,256,512]``.  Every
volume with a preset in ``state_files/`` is read with that preset, from three views (azimuth
0, 120 and 240 degrees at 20 degrees of elevation), at each size; per view the relative spread
of ``E_s`` (``(max - min) / mean``) and the absolute spread of ``E_t`` (``max - min``) are
recorded, together with the time of the re-composites the transparency measure made (one per
enclosing layer read against the view without it).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VIEWS = ((0.0, 20.0), (120.0, 20.0), (240.0, 20.0))


def _scene(data: Path, name: str):
    from dvr_perception.structures.io import attach_labels, load_spec
    from dvr_perception.volume.io import load_volume

    volume = load_volume(data / f"{name}.nhdr")
    spec = load_spec(REPO / "state_files" / f"{name}.json")
    return attach_labels(volume, spec), spec


def measure_volume(data: Path, name: str, sizes, log) -> dict:
    """Return ``{"views": [...], "E_s_spread": max relative, "E_t_spread": max absolute}``."""
    import numpy as np

    from dvr_perception.measures import shape, transparency
    from dvr_perception.rays import Camera
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze

    volume, spec = _scene(data, name)
    curvature = curvature_source(volume, spec)
    views = []
    for azimuth, elevation in VIEWS:
        row = {"azimuth": azimuth, "elevation": elevation, "sizes": []}
        for n in sizes:
            cam = Camera.from_view(volume.bounds, azimuth=azimuth, elevation=elevation,
                                   width=n, height=n)  # fmt: skip
            t0 = time.perf_counter()
            a = analyze(volume, spec, cam, curvature=curvature)
            t_frame = time.perf_counter() - t0
            t0 = time.perf_counter()
            e_s = shape(a, spec).E_s
            t_shape = time.perf_counter() - t0
            t0 = time.perf_counter()
            trn = transparency(a, spec)
            t_trn = time.perf_counter() - t0
            t0 = time.perf_counter()
            plain = transparency(a, spec, enclosure="plain")
            t_plain = time.perf_counter() - t0
            row["sizes"].append({
                "size": n, "E_s": e_s, "E_t": trn.E_t, "E_t_plain": plain.E_t,
                "analyze_s": t_frame, "shape_s": t_shape, "transparency_s": t_trn,
                "transparency_plain_s": t_plain,
            })  # fmt: skip
            log(f"{name} az {azimuth:g} {n}px: E_s {e_s:.4f} E_t {trn.E_t:.4f} "
                f"(plain {plain.E_t:.4f}) frame {t_frame:.2f}s E_t {t_trn:.2f}s "
                f"plain {t_plain:.2f}s")  # fmt: skip
        e_s = np.array([r["E_s"] for r in row["sizes"]])
        e_t = np.array([r["E_t"] for r in row["sizes"]])
        row["E_s_spread"] = float((e_s.max() - e_s.min()) / max(e_s.mean(), 1e-12))
        row["E_t_spread"] = float(e_t.max() - e_t.min())
        views.append(row)
    return {
        "views": views,
        "E_s_spread": max(v["E_s_spread"] for v in views),
        "E_t_spread": max(v["E_t_spread"] for v in views),
    }


def main(argv=None) -> int:
    """Measure the volumes named (default: every preset with shared data) and write JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    p.add_argument("--out", default=str(REPO / "benchmarks" / "size_invariance.json"))
    p.add_argument("--volumes", default=None, help="comma-separated names (default: all)")
    p.add_argument("--sizes", default="96,128,256,512")
    args = p.parse_args(argv)
    data = Path(args.data)
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.volumes:
        names = args.volumes.split(",")
    else:
        names = sorted(f.stem for f in (REPO / "state_files").glob("*.json")
                       if (data / f"{f.stem}.nhdr").is_file())  # fmt: skip

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    out = {"sizes": sizes, "views": [list(v) for v in VIEWS], "volumes": {}}
    for name in names:
        out["volumes"][name] = measure_volume(data, name, sizes, log)
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
