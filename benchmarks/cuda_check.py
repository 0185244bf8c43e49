"""The CUDA back end on a real GPU: the same results as numba, and its frame and optimisation times.

Run on a machine with an NVIDIA GPU, numba-cuda (``pip install 'dvr-perception[gpu]'``) and
the shared data (VTK is not needed)::

    python -m benchmarks.cuda_check --data ../shared/data --out cuda_check.json
    python -m benchmarks.cuda_check --data ../shared/data --big --optimize   # + 512^3, 1024^3

It prints (and with ``--out`` writes) one JSON object:

* ``device``: the GPU, numba and numba-cuda versions, numba's CPU threads.
* ``equal``: per shared volume (``--volumes``, at ``--size``, with the curvature volume and
  the re-evaluation cache), the largest difference of every buffer and of the E terms between
  ``backend="cuda"`` and ``backend="numba"``, whether the caches are equal, and ``passed``
  (buffers within 1e-5, E terms within 1e-6).
* ``frames``: per volume, median seconds of ``--repeat`` analyses on each back end: ``frame``
  (with the cache, as the optimiser's first pass), ``measure`` (no cache, as ``measure``
  pays), ``measure_new_camera`` (the same with the camera moved a hair every time: the rays
  are made and uploaded, as when the user turns the view; ``measure`` reuses them) and
  ``render`` (no cache, rays stop at early termination); ``first`` is the first call
  (kernel compilation included).
* with ``--big``: cthead up-sampled to 512 x 512 x 452 (``--resample 2,2,4``) and to
  1024 x 1024 x 904 (``4,4,8``; cuda only, one numba frame); with ``--optimize``: the whole
  default optimisation (three stages) of the 512 x 512 x 452 CT on each back end.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

FIELDS = ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature",
          "importance_accumulated")  # fmt: skip


def _load(path: Path, size: int, resample: str | None = None):
    from dvr_perception.cli import build_parser
    from dvr_perception.inputs import load_inputs

    argv = ["bench", str(path), "--size", str(size)]
    if resample:
        argv += ["--resample", resample]
    return load_inputs(build_parser().parse_args(argv))


def _diff(a, b) -> dict:
    out = {}
    for f in FIELDS:
        x, y = np.asarray(getattr(a, f), float), np.asarray(getattr(b, f), float)
        same_nan = np.isnan(x) & np.isnan(y)
        out[f] = float(np.max(np.where(same_nan, 0.0, np.abs(x - y)))) if x.size else 0.0
    return out


def _terms(analysis, spec) -> dict:
    from dvr_perception.measures import all_measures

    m = all_measures(analysis, spec)
    return {"E_v": m.visibility.E_v, "E_s": m.shape.E_s, "E_t": m.transparency.E_t}


def _median(fn, repeat: int) -> float:
    from dvr_perception._timing import median_time

    return median_time(fn, repeat)


def _equal(inputs, curv) -> dict:
    from dvr_perception.rays.engine import analyze

    vol, spec, cam = inputs.volume, inputs.spec, inputs.camera
    a = analyze(vol, spec, cam, curvature=curv, backend="numba")
    b = analyze(vol, spec, cam, curvature=curv, backend="cuda")
    buffers = _diff(a, b)
    ta, tb = _terms(a, spec), _terms(b, spec)
    terms = {k: abs(ta[k] - tb[k]) for k in ta}
    caches = {f: bool(np.array_equal(getattr(a.cache, f), getattr(b.cache, f)))
              for f in ("start", "count", "lut")}  # fmt: skip
    return {
        "buffers": buffers,
        "E": terms,
        "E_numba": ta,
        "caches_equal": caches,
        "rays_differing": int(np.count_nonzero(np.any(a.image != b.image, axis=-1))),
        "passed": max(buffers.values()) <= 1e-5 and max(terms.values()) <= 1e-6,
    }


def _frames(inputs, curv, repeat: int, backends=("cuda", "numba")) -> dict:
    from dvr_perception.rays.engine import analyze

    vol, spec, cam = inputs.volume, inputs.spec, inputs.camera
    out = {"dims": list(vol.dims), "size": [cam.width, cam.height]}
    for backend in backends:

        def run(b=backend, camera=cam, **kw):
            return analyze(vol, spec, camera, backend=b, **kw)

        t0 = time.perf_counter()
        run(curvature=curv)  # compiles, uploads
        first = time.perf_counter() - t0
        run(build_cache=False, occlusion_free=False)
        moved = iter(_nudged(cam, repeat))
        out[backend] = {
            "first": first,
            "frame": _median(lambda r=run: r(curvature=curv), repeat),
            "measure": _median(lambda r=run: r(curvature=curv, build_cache=False), repeat),
            "measure_new_camera": _median(
                lambda r=run, m=moved: r(camera=next(m), curvature=curv, build_cache=False),
                repeat,
            ),
            "render": _median(lambda r=run: r(build_cache=False, occlusion_free=False), repeat),
        }
    return out


def _nudged(cam, count: int) -> list:
    """``count`` cameras a hair beside ``cam``: every analysis makes (and uploads) its rays."""
    from dataclasses import replace

    pos, focal = np.asarray(cam.position, float), np.asarray(cam.focal_point, float)
    step = 1e-4 * float(np.linalg.norm(pos - focal))
    return [replace(cam, position=tuple(pos + (i + 1) * step)) for i in range(count)]


def _optimize(inputs, curv, backend: str) -> dict:
    from dvr_perception.optimize import optimize

    t0 = time.perf_counter()
    res = optimize(inputs.volume, inputs.spec, inputs.camera, curvature=curv, backend=backend)
    return {"seconds": time.perf_counter() - t0, "E_initial": res.initial["E"],
            "E_final": res.final["E"], "nfev": res.nfev}  # fmt: skip


def main(argv=None) -> int:
    """Run the checks; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="../shared/data", help="shared data folder")
    p.add_argument("--volumes", default="engine,cthead", help="shared volumes to compare")
    p.add_argument("--size", type=int, default=512, help="image size (default 512)")
    p.add_argument("--repeat", type=int, default=5, help="timed repeats (default 5)")
    p.add_argument("--big", action="store_true", help="also the 512^3 and 1024^3 CTs")
    p.add_argument("--optimize", action="store_true", help="also time the whole optimisation")
    p.add_argument("--out", help="also write the JSON here")
    args = p.parse_args(argv)

    import numba

    from dvr_perception.rays import _cuda
    from dvr_perception.rays.curvature_field import curvature_source

    ck = _cuda.kernels()  # one clear error without numba-cuda or a device
    from numba import cuda

    dev = cuda.current_context().device
    name = getattr(dev, "name", "simulator")
    report = {
        "device": {
            "name": name.decode() if isinstance(name, bytes) else str(name),
            "compute_capability": list(getattr(dev, "compute_capability", ())),
            "numba": numba.__version__,
            "cuda_implementation": getattr(cuda, "implementation", "?"),
            "numba_threads": int(numba.get_num_threads()),
            "block": list(ck.BLOCK),
        },
        "equal": {},
        "frames": {},
    }
    data = Path(args.data)
    for name in filter(None, args.volumes.split(",")):
        inputs = _load(data / f"{name}.nhdr", args.size)
        curv = curvature_source(inputs.volume, inputs.spec)
        report["equal"][name] = _equal(inputs, curv)
        report["frames"][name] = _frames(inputs, curv, args.repeat)
        print(name, json.dumps(report["equal"][name]["passed"]), file=sys.stderr)
    if args.big or args.optimize:
        inputs = _load(data / "cthead.nhdr", args.size, "2,2,4")
        curv = curvature_source(inputs.volume, inputs.spec)
        if args.big:
            report["equal"]["cthead_512x512x452"] = _equal(inputs, curv)
            report["frames"]["cthead_512x512x452"] = _frames(inputs, curv, args.repeat)
        if args.optimize:
            report["optimize_cthead_512x512x452"] = {
                b: _optimize(inputs, curv, b) for b in ("cuda", "numba")
            }
        del inputs, curv
    if args.big:
        inputs = _load(data / "cthead.nhdr", args.size, "4,4,8")
        curv = curvature_source(inputs.volume, inputs.spec)
        report["frames"]["cthead_1024x1024x904"] = _frames(inputs, curv, args.repeat, ("cuda",))
    report["passed"] = all(e["passed"] for e in report["equal"].values())
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0 if report["passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
