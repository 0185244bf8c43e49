"""The CUDA back end against the CPU engine, under numba's CUDA simulator (no GPU needed).

``NUMBA_ENABLE_CUDASIM=1`` must be set before ``numba.cuda`` is first imported, and the rest
of the suite imports it without (doctest collection of ``rays/_cuda_kernels.py``), so the
comparisons run in one subprocess per module (the simulator runs every thread in Python:
16^3 volumes, 12 x 10 pixels).  Each case reports the largest difference of every buffer
and of the E terms between ``backend="cuda"`` and ``backend="numba"``; the tests hold them
to 1e-5 (buffers) and 1e-6 (E terms) and check that the cases are not trivial.

Also here, without the simulator: the clear errors of ``backend="cuda"`` where it cannot run,
how ``auto`` chooses, and that the core imports and runs with ``vtkmodules`` unavailable.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dvr_perception.errors import DVRInputError
from tests.conftest import _missing

REPO = Path(__file__).resolve().parents[2]

_SIM = r"""
import json
import numpy as np
from dvr_perception.errors import DVRInputError
from dvr_perception.measures import all_measures
from dvr_perception.optimize import optimize
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze, analyze_views, reevaluate
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.structures import make_phantom
from dvr_perception.volume import Volume

FIELDS = ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature",
          "importance_accumulated")
CACHE = ("start", "count", "lut", "shading", "curvature")


def diff(a, b):
    out = {}
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape and x.dtype == y.dtype, (f, x.shape, y.shape)
        both = np.isnan(x) & np.isnan(y) if x.dtype.kind == "f" else np.zeros(x.shape, bool)
        d = np.abs(x.astype(float) - y.astype(float))
        out[f] = float(np.max(np.where(both, 0.0, d))) if d.size else 0.0
    return out


def e_terms(res, spec):
    m = all_measures(res, spec, parallel=False)
    return {"E_v": m.visibility.E_v, "E_s": m.shape.E_s, "E_t": m.transparency.E_t}


def compare(vol, spec, cam, **kw):
    a = analyze(vol, spec, cam, backend="numba", **kw)
    b = analyze(vol, spec, cam, backend="cuda", **kw)
    rec = {"backend": b.stats["backend"], "buffers": diff(a, b),
           "walked": [a.stats["samples_walked"], b.stats["samples_walked"]],
           "hit": int(np.count_nonzero(a.accumulated > 0.05)),
           "structures_seen": int(np.count_nonzero(np.bitwise_or.reduce(a.present.ravel())
                                                    >> np.arange(len(spec.structures)) & 1))}
    if kw.get("occlusion_free", True):
        ea, eb = e_terms(a, spec), e_terms(b, spec)
        rec["E"] = {k: abs(ea[k] - eb[k]) for k in ea}
        rec["E_numba"] = ea
    if a.cache is not None:
        rec["cache_equal"] = {f: bool(np.array_equal(getattr(a.cache, f), getattr(b.cache, f)))
                              for f in CACHE if f != "shading"}
        # column 1 of an entry marked unset (65535 in column 0) is never read: not compared
        sa, sb = a.cache.shading, b.cache.shading
        rec["cache_equal"]["shading"] = bool(
            np.array_equal(sa[:, 0], sb[:, 0])
            and np.array_equal(sa[sa[:, 0] != 65535, 1], sb[sb[:, 0] != 65535, 1]))
        rec["shading_set"] = int(np.count_nonzero(sa[:, 0] != 65535))
        rec["cache_equal"]["steps"] = bool(np.array_equal(a.cache.lazy["steps"],
                                                          b.cache.lazy["steps"]))
        rec["cache_entries"] = int(len(a.cache.lut))
        k = len(spec.structures)
        kw2 = {"opacities": np.linspace(0.2, 0.9, k), "light_direction": (0.3, 0.4, 0.8)}
        rec["reevaluated"] = diff(reevaluate(a.cache, **kw2), reevaluate(b.cache, **kw2))
    return rec


def labels_scene():
    z, y, x = np.mgrid[:16, :16, :17].astype(float)
    d = np.sqrt((x - 8) ** 2 + (y - 7.5) ** 2 + (z - 7) ** 2)
    data = np.clip(220 - 14 * d, 0, 255).astype(np.uint8)
    labels = np.zeros(data.shape, np.uint16)
    labels[5:10, 5:10, 6:11] = 7
    vol = Volume(data, labels=labels)
    spec = StructureSpec((Structure("shell", 0.3, (1, 0.5, 0), range=(60, 160), edge=0.2),
                          Structure("box", 0.9, (0, 0, 1), label=7)))
    return vol, spec


def slab_scene():  # an opaque slab in front of a thin layer, seen from above: skipping jumps
    data = np.zeros((24, 12, 12), np.uint8)
    data[8:] = 220
    data[2:4] = 100
    spec = StructureSpec((Structure("layer", 0.05, (1, 0, 0), range=(60, 140), edge=0.0),
                          Structure("slab", 1.0, (1, 1, 1), range=(180, 255), edge=0.0)),
                         rendering=RenderSettings(shade=False))
    vol = Volume(data)
    cx, cy, cz = vol.center
    cam = Camera(position=(cx, cy, cz + 100.0), focal_point=(cx, cy, cz),
                 parallel_projection=True, parallel_scale=4.0, width=12, height=10)
    return vol, spec, cam


out = {}
svol, sspec, scam = slab_scene()
out["skipping"] = compare(svol, sspec, scam, build_cache=False)
out["skipping_exact"] = compare(svol, sspec, scam, build_cache=False, exact=True)
vol, spec = make_phantom(size=16)
cam = Camera.from_view(vol.bounds, width=12, height=10)
side = Camera.from_view(vol.bounds, width=12, height=10, azimuth=70.0, elevation=20.0)
flat = StructureSpec(spec.structures, spec.background, RenderSettings(shade=False))
out["shaded_cache"] = compare(vol, spec, cam)
out["unshaded"] = compare(vol, flat, cam, build_cache=False)
out["unshaded_cache"] = compare(vol, flat, side)
lvol, lspec = labels_scene()
out["labels"] = compare(lvol, lspec, cam)
rng = np.random.default_rng(3)
curv = rng.random(vol.data.shape).astype(np.float32) * (rng.random(vol.data.shape) < 0.5)
out["curvature"] = compare(vol, spec, side, curvature=curv)
out["render_only"] = compare(vol, spec, cam, build_cache=False, occlusion_free=False)
views = [cam, side]
va = analyze_views(vol, spec, views, backend="numba", build_cache=True)
vb = analyze_views(vol, spec, views, backend="cuda", build_cache=True)
out["views"] = {"backend": [v.stats["backend"] for v in vb],
                "buffers": [diff(a, b) for a, b in zip(va, vb)],
                "E": [{k: abs(x - y) for (k, x), y in zip(e_terms(a, spec).items(),
                                                          e_terms(b, spec).values())}
                      for a, b in zip(va, vb)]}
lens = ("rect", 2, 2, 8, 7)
runs = {}
for backend in ("numba", "cuda"):
    seen = []
    r = optimize(vol, spec, cam, region=lens, max_iter=1, backend=backend,
                 callback=lambda it: seen.append(it.stage))
    runs[backend] = {"initial": r.initial["E"], "final": r.final["E"],
                     "opacities": [s.opacity for s in r.spec.structures],
                     "stages": sorted(set(seen)), "records": [s.name for s in r.stages],
                     "image": r.analyses[1].image}
out["optimize"] = {
    "stages": runs["cuda"]["stages"], "records": runs["cuda"]["records"],
    "initial": abs(runs["cuda"]["initial"] - runs["numba"]["initial"]),
    "final": abs(runs["cuda"]["final"] - runs["numba"]["final"]),
    "opacities": float(np.max(np.abs(np.subtract(runs["cuda"]["opacities"],
                                                 runs["numba"]["opacities"])))),
    "image": float(np.max(np.abs(runs["cuda"]["image"] - runs["numba"]["image"]))),
}
import warnings

from dvr_perception.errors import DVRWarning

away = Camera(position=(500, 500, 500), focal_point=(1000, 1000, 1000), width=6, height=5)
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always", DVRWarning)
    e = analyze(vol, spec, away, backend="cuda", build_cache=True)
out["empty"] = {"warned": [str(w.message)[:40] for w in seen], "backend": e.stats["backend"],
                "image": e.image.reshape(-1, 3)[0].tolist(), "any": bool(e.accumulated.any()),
                "entries": int(len(e.cache.lut)),
                "bg": list(spec.background),
                "reevaluated": bool(reevaluate(e.cache, opacities=[1.0] * len(spec.structures))
                                    .accumulated.any())}
out["auto"] = analyze(vol, spec, cam, build_cache=False).stats["backend"]
# the second analysis with the same camera and other opacities uploads only the table that
# changed (the rays, volumes and other tables stay on the device) and reuses the work arrays
from numba import cuda as ncuda

from dvr_perception.rays import _cuda

k = len(spec.structures)
analyze(vol, spec, side, backend="cuda", build_cache=False, opacities=[0.3] * k)
kept = dict(_cuda._SCRATCH)
uploads = []
upload = ncuda.to_device
ncuda.to_device = lambda a, *x, **y: (uploads.append(list(np.shape(a))), upload(a, *x, **y))[1]
b = analyze(vol, spec, side, backend="cuda", build_cache=False, opacities=[0.7] * k)
ncuda.to_device = upload
a = analyze(vol, spec, side, backend="numba", build_cache=False, opacities=[0.7] * k)
ea, eb = e_terms(a, spec), e_terms(b, spec)
out["reuse"] = {"uploads": uploads, "work": sorted(kept),
                "same_work": sorted(q for q in kept if _cuda._SCRATCH[q] is kept[q]),
                "buffers": diff(a, b), "E": {t: abs(ea[t] - eb[t]) for t in ea},
                "hit": int(np.count_nonzero(a.accumulated > 0.05))}
# a volume the CPU analyses in bricks (forced: the plan bricks only what does not fit the
# limit, issue 31) is analysed whole on the GPU, with the same buffers
a = analyze(vol, spec, side, backend="numba", brick=(8, 8, 8), build_cache=True)
b = analyze(vol, spec, side, backend="cuda", build_cache=True)
p = analyze_views(vol, spec, [side, cam], backend="cuda", build_cache=True)
out["large"] = {"cpu_bricks": a.stats.get("bricks", 0), "backend": b.stats["backend"],
                "buffers": diff(a, b), "views": [v.stats["backend"] for v in p]}
from dvr_perception.rays import engine

big, bspec = make_phantom(size=96)
_, _, _, lut, _, _, memb, seg = engine._scene(big, bspec, side, "numba")
whole = engine._plan(big, bspec, side, seg, lut, memb, False, True, None, None)["whole"]
cap = int(whole * 0.9)  # too small for the whole volume, enough for bricks of 32^3 cells
plan = engine._plan(big, bspec, side, seg, lut, memb, False, True, cap, None)
assert plan["mode"] == "bricks", plan
try:  # fits in bricks only: cuda says so
    analyze(big, bspec, side, backend="cuda", memory_limit=cap, build_cache=True)
    out["too_large"] = "no error"
except DVRInputError as exc:
    out["too_large"] = str(exc)
try:
    analyze(vol, spec, cam, backend="cuda", brick=(8, 8, 8), build_cache=True)
    out["brick"] = "no error"
except DVRInputError as exc:
    out["brick"] = str(exc)
import contextlib
import io

from dvr_perception.cli import main
from dvr_perception.rays import vtk_process, vtk_reference


@contextlib.contextmanager
def no_vtk_frames(*_):  # bench's VTK reference frames: not what is compared here
    yield lambda: 0.25


vtk_reference.vtk_frame_timer = no_vtk_frames
vtk_process.vtk_frame_process = no_vtk_frames


def cli(*argv):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main([*argv, "--json"])
    assert code == 0, (argv, code)
    return json.loads(buf.getvalue())


reports = {b: cli("measure", "phantom", "--size", "12x10", "--backend", b)
           for b in ("numba", "cuda")}
out["cli_measure"] = {k: abs(reports["cuda"][k] - reports["numba"][k])
                      for k in ("E_v", "E_s", "E_t")}
out["cli_measure_E_v"] = reports["numba"]["E_v"]
benches = {b: cli("bench", "--size", "12x10", "--repeat", "1", "--backend", b)
           for b in ("numba", "cuda")}
out["bench"] = {b: {"keys": sorted(r), "backend": r["backend"]} for b, r in benches.items()}
print(json.dumps(out))
"""


def _env(**extra) -> dict:
    env = dict(os.environ, **extra)
    env.pop("DVR_PERCEPTION_NO_NUMBA", None)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


@pytest.fixture(scope="module")
def sim() -> dict:
    """The comparisons, run once in a subprocess under the CUDA simulator."""
    run = subprocess.run(
        [sys.executable, "-W", "error", "-c", _SIM],
        env=_env(NUMBA_ENABLE_CUDASIM="1"),
        capture_output=True,
        text=True,
        timeout=1800,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-4000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


CASES = (
    "shaded_cache",
    "unshaded",
    "unshaded_cache",
    "labels",
    "curvature",
    "render_only",
    "skipping",
    "skipping_exact",
)


@pytest.mark.parametrize("case", CASES)
def test_cuda_equals_numba(sim, case):
    rec = sim[case]
    assert rec["backend"] == "cuda"
    assert rec["hit"] >= 10  # a case that shows something
    for field, d in rec["buffers"].items():
        assert d <= 1e-5, (field, d)
    if "E" in rec:
        for term, d in rec["E"].items():
            assert d <= 1e-6, (term, d)
        assert rec["E_numba"]["E_v"] > 0  # not a case where every term is trivially 0
    if "cache_equal" in rec:
        assert rec["cache_entries"] > 50
        assert rec["shading_set"] > 10 or "unshaded" in case
        assert all(rec["cache_equal"].values()), rec["cache_equal"]
        for field, d in rec["reevaluated"].items():
            assert d <= 1e-5, (field, d)


def test_the_skipping_walk_is_the_numba_one(sim):
    """The walk behind early ray termination skips on the GPU as on the CPU (D8)."""
    skip, exact = sim["skipping"]["walked"], sim["skipping_exact"]["walked"]
    assert skip[0] == skip[1]
    assert exact[0] == exact[1]
    assert skip[0] < 0.7 * exact[0]
    assert sim["skipping"]["structures_seen"] == 2  # the layer behind the slab is found


def test_cases_cover_what_they_claim(sim):
    assert sim["labels"]["structures_seen"] == 2  # the label structure is met
    assert sim["curvature"]["buffers"]["curvature"] <= 1e-5
    assert sim["shaded_cache"]["structures_seen"] >= 2


def test_two_views(sim):
    rec = sim["views"]
    assert rec["backend"] == ["cuda", "cuda"]
    for view in rec["buffers"]:
        assert max(view.values()) <= 1e-5, view
    for view in rec["E"]:
        assert max(view.values()) <= 1e-6, view


def test_optimize_runs_the_three_stages_on_cuda_with_a_lens(sim):
    rec = sim["optimize"]
    assert rec["stages"] == sorted(["opacity", "lighting", "colour"])
    assert set(rec["records"]) == {"opacity", "lighting", "colour"}
    assert rec["initial"] <= 1e-6
    assert rec["final"] <= 1e-6
    assert rec["opacities"] <= 1e-6
    assert rec["image"] <= 1e-5


def test_cli_measure_and_bench_take_the_backend(sim):
    assert sim["cli_measure_E_v"] > 0
    assert max(sim["cli_measure"].values()) <= 1e-6, sim["cli_measure"]
    bench = sim["bench"]
    assert bench["cuda"]["backend"] == "cuda"
    assert bench["numba"]["backend"] == "numba"
    assert bench["cuda"]["keys"] == bench["numba"]["keys"]
    assert "frame_s" in bench["cuda"]["keys"]


def test_cli_backend_choices_are_the_engines():
    from dvr_perception.cli._backend import BACKENDS as CLI
    from dvr_perception.rays.engine import BACKENDS

    assert CLI == BACKENDS


def test_a_volume_the_cpu_bricks_is_analysed_whole_on_the_gpu(sim):
    rec = sim["large"]
    assert rec["cpu_bricks"] >= 1  # the CPU took the bricked path
    assert rec["backend"] == "cuda"
    assert rec["views"] == ["cuda", "cuda"]
    assert max(rec["buffers"].values()) <= 1e-5, rec["buffers"]
    assert sim["too_large"].startswith("memory_limit: volume 'phantom' needs a bricked"), sim[
        "too_large"
    ]


def test_a_camera_that_sees_nothing(sim):
    rec = sim["empty"]
    assert rec["backend"] == "cuda"
    assert len(rec["warned"]) == 1
    assert rec["warned"][0].startswith("camera sees none of volume")
    assert not rec["any"]
    assert rec["entries"] == 0
    assert not rec["reevaluated"]
    assert rec["image"] == pytest.approx(rec["bg"], abs=1e-6)  # the background


def test_a_second_analysis_reuses_what_is_on_the_device(sim):
    rec = sim["reuse"]
    assert rec["hit"] >= 10
    assert max(rec["buffers"].values()) <= 1e-5, rec["buffers"]
    assert max(rec["E"].values()) <= 1e-6, rec["E"]
    # only the render opacities' table changed: one small upload, no rays, no volume
    assert len(rec["uploads"]) == 1, rec["uploads"]
    assert len(rec["uploads"][0]) == 1, rec["uploads"]
    assert rec["uploads"][0][0] < 1000, rec["uploads"]
    assert "rgba" in rec["work"]
    assert "state" in rec["work"]
    assert rec["same_work"] == rec["work"]


def test_auto_never_takes_the_simulator_and_bricks_are_refused(sim):
    assert sim["auto"] == "numba"
    assert sim["brick"].startswith("brick: the cuda back end")


def test_cuda_without_a_device_is_one_clear_error(monkeypatch):
    from dvr_perception.rays._cuda import numpy_for_numba_cuda

    numpy_for_numba_cuda()
    from numba import cuda

    from dvr_perception.rays.camera import Camera
    from dvr_perception.rays.engine import analyze
    from dvr_perception.structures import make_phantom

    monkeypatch.setattr(cuda, "is_available", lambda: False)
    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=4, height=4)
    with pytest.raises(DVRInputError, match=r"^backend: 'cuda' ") as err:
        analyze(vol, spec, cam, backend="cuda", build_cache=True)
    assert "dvr-perception[gpu]" in str(err.value)
    from dvr_perception.optimize import optimize

    with pytest.raises(DVRInputError, match=r"^backend: 'cuda' "):
        optimize(vol, spec, cam, backend="cuda", max_iter=1)
    with pytest.raises(DVRInputError, match=r"^backend: expected one of"):
        analyze(vol, spec, cam, backend="gpu", build_cache=True)


def test_auto_prefers_a_device_and_falls_back(monkeypatch):
    from dvr_perception.rays import _cuda, engine

    nk = engine._numba_kernels()
    assert nk is not None
    monkeypatch.delenv("DVR_PERCEPTION_NO_CUDA", raising=False)  # tests/conftest.py sets it
    monkeypatch.setattr(_cuda, "_AUTO", [True])
    assert engine._kind("auto", nk) == "cuda"
    assert engine._kind("numba", nk) == "numba"
    assert engine._kind("auto", None) == "numpy"
    monkeypatch.setenv("DVR_PERCEPTION_NO_CUDA", "1")
    assert engine._kind("auto", nk) == "numba"
    monkeypatch.delenv("DVR_PERCEPTION_NO_CUDA")
    monkeypatch.setattr(_cuda, "_AUTO", [False])
    assert engine._kind("auto", nk) == "numba"
    # no NVIDIA driver: looked up without importing numba.cuda, and no
    monkeypatch.setattr(_cuda, "_AUTO", [])
    monkeypatch.setattr(_cuda, "_no_nvidia_driver", lambda: True)
    assert _cuda.auto_usable() is False
    assert _cuda._AUTO == [False]


_LOWER = r"""
# Lower the kernels to NVVM IR for a compute capability 9.0 device, with the argument types
# the engine passes (its launches are intercepted): what a real GPU compiles, minus NVVM.
import json
import numpy as np
from dvr_perception.rays import _cuda, engine

_cuda.numpy_for_numba_cuda()  # numpy >= 2.5: before numba.cuda
import numba
from numba import cuda, types
from numba.cuda.compiler import compile_cuda
import numba.cuda.dispatcher as dispatcher
from dvr_perception.rays import _cuda_kernels as ck
from dvr_perception.rays.camera import Camera
from dvr_perception.structures import make_phantom

assert cuda.implementation == "NVIDIA", cuda.implementation


class Device:
    compute_capability = (9, 0)


dispatcher.get_current_device = lambda: Device()  # device functions ask for it


class Host(np.ndarray):
    def copy_to_host(self):
        return np.asarray(self).copy()

    def copy_to_device(self, a):
        self[...] = a


lowered = []


class Launch:
    def __init__(self, kernel):
        self.kernel = kernel

    def __getitem__(self, config):
        def run(*args):
            tys = tuple(numba.typeof(np.asarray(a) if isinstance(a, Host) else a) for a in args)
            res = compile_cuda(self.kernel.py_func, types.void, tys, cc=(9, 0))
            lowered.append([self.kernel.py_func.__name__, len(res.library.get_llvm_str())])
        return run


class Kernels:
    BLOCK = ck.BLOCK
    walk = Launch(ck.walk)
    finish = Launch(ck.finish)
    compact = Launch(ck.compact)


_cuda.kernels = lambda: Kernels
_cuda.to_device = lambda a, keep=False, pool="volume": np.ascontiguousarray(a).view(Host)
_cuda.table = lambda a: np.ascontiguousarray(a).view(Host)
_cuda.check_fits = lambda need: None
cuda.device_array = lambda shape, dtype: np.zeros(shape, dtype).view(Host)
engine._pick_backend = lambda backend: engine._numba_kernels()
vol, spec = make_phantom(size=16)
cam = Camera.from_view(vol.bounds, width=12, height=10)
engine.analyze(vol, spec, cam, backend="cuda", build_cache=True)
engine.analyze(vol, spec, cam, backend="cuda", build_cache=False, occlusion_free=False,
               curvature=np.ones(vol.data.shape, np.float32))
print(json.dumps(lowered))
"""


_IMPLEMENTATION = """
from dvr_perception.rays._cuda import numpy_for_numba_cuda
numpy_for_numba_cuda()
from numba import cuda
print(cuda.implementation)
"""


@pytest.fixture(scope="module")
def numba_cuda():
    """numba-cuda (the ``gpu`` extra's CUDA target): skips without it, fails under CI."""
    run = subprocess.run(
        [sys.executable, "-c", _IMPLEMENTATION],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if run.stdout.strip() != "NVIDIA":
        _missing("numba-cuda is not installed (pip install numba-cuda)")
    return True


def test_kernels_lower_for_a_real_gpu(numba_cuda):
    run = subprocess.run(
        [sys.executable, "-W", "error", "-c", _LOWER],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-4000:]
    lowered = json.loads(run.stdout.strip().splitlines()[-1])
    assert [name for name, _ in lowered] == ["walk", "finish", "compact", "walk", "finish"]
    assert all(size > 10_000 for _, size in lowered)


_NO_VTK = r"""
import sys

class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "vtk" or name.startswith(("vtkmodules", "vtk.")):
            raise ImportError(f"vtkmodules blocked: {name}")
        return None

sys.meta_path.insert(0, Block())
try:
    import vtkmodules  # noqa: F401
except ImportError:
    pass
else:
    raise SystemExit("the blocker did not block")
import dvr_perception.measures
import dvr_perception.optimize
import dvr_perception.rays
from dvr_perception.measures import all_measures
from dvr_perception.optimize import optimize
from dvr_perception.rays import Camera, analyze
from dvr_perception.structures import make_phantom

import os
import tempfile

from dvr_perception.volume import load_volume, save_volume

vol, spec = make_phantom(size=16)
path = os.path.join(tempfile.mkdtemp(), "phantom.nhdr")  # NRRD: read and written without VTK
save_volume(vol, path)
assert (load_volume(path).data == vol.data).all()
cam = Camera.from_view(vol.bounds, width=12, height=10)
m = all_measures(analyze(vol, spec, cam, build_cache=True), spec)
r = optimize(vol, spec, cam, stages=("opacity",), max_iter=1)
print(sorted(m for m in sys.modules if m.startswith(("vtk", "pyvista"))), m.visibility.E_v > 0,
      r.final["E"] <= r.initial["E"])
"""


def test_core_imports_and_runs_without_vtk():
    run = subprocess.run(
        [sys.executable, "-W", "error", "-c", _NO_VTK],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-4000:]
    assert run.stdout.strip().splitlines()[-1] == "[] True True"


def test_volume_package_still_offers_the_vtk_readers():
    import dvr_perception.volume as v

    assert callable(v.load_volume)
    assert callable(v.to_vtk_image)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = v.nothing
    assert v.phantom_volume(size=16).data.shape == (16, 16, 16)
