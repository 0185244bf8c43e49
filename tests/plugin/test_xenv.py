"""ParaView's Python and this venv give the same E terms on every shared volume (issue 18.5).

One pvpython process (numpy 1.24, VTK 9.2 with ParaView 5.11) computes E_v, E_s and E_t of all
16 shared volumes, each with its preset spec at the preset's view and at 60,20, at SIZE x SIZE,
with the volume passed through VTK and the spec through JSON as the *Perception Measures*
filter receives them (``test_paraview.py`` checks the filter itself against the library).  The
library computes the same scenes here (numpy 2.x, VTK 9.7) while ParaView runs; every term must
agree to ``CROSS_ENV_ABS``.

Both sides use the same back end: numba by default, numpy with ``DVR_PERCEPTION_NO_NUMBA=1``
(the numpy path moved encoded normals and E_s by 1.3e-4 on fuel between numpy 1.24 and 2.4
before ``rays._grid.normal_codes`` decided angles on rounding boundaries with the C library).
The file is named to run after the other ParaView tests (numba's cache is warm by then).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from dvr_perception._numba import kernels
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import load_spec, spec_to_dict
from dvr_perception.volume import load_volume
from tests.plugin.conftest import CROSS_ENV_ABS, MARK

REPO = Path(__file__).resolve().parents[2]
SIZE = 64
#: The preset's view (the spec's, else VTK's default) and one oblique view.
VIEWS = ("preset", (60.0, 20.0, 1.0))
TERMS = ("E_v", "E_s", "E_t")

SCRIPT = f"""
import json, sys, time
T0 = time.perf_counter()
from dvr_perception._paraview_compat import setup
setup()
import numpy
from dvr_perception._numba import kernels
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import spec_from_dict
from dvr_perception.volume import load_volume
from dvr_perception.volume.convert import from_vtk_image, to_vtk_image
jobs = json.load(open(sys.argv[1]))
out = {{"numpy": numpy.__version__,
        "numba": kernels("dvr_perception.rays._numba_grid") is not None, "E": {{}}}}
for job in jobs:
    # the volume through VTK, the spec through JSON: as the Perception Measures filter gets them
    vol = from_vtk_image(to_vtk_image(load_volume(job["volume"])), name="input")
    spec = spec_from_dict(json.loads(job["spec"]), source="spec_json")
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    for key, camera in job["cameras"].items():
        res = analyze(vol, spec, Camera.from_dict(camera), curvature=curv, build_cache=False)
        out["E"][key] = [visibility(res, spec).E_v, shape(res, spec).E_s,
                         transparency(res, spec).E_t]
        print("@@T", key, round(time.perf_counter() - T0, 2), flush=True)
print({MARK!r} + json.dumps(out), flush=True)
"""


def _cameras(vol, spec) -> dict:
    out = {}
    for view in VIEWS:
        az, el, zoom = (spec.view or (0.0, 0.0, 1.0)) if view == "preset" else view
        cam = Camera.from_view(
            vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE, height=SIZE
        )
        out["preset" if view == "preset" else f"{az:g},{el:g}"] = cam
    return out


def test_paraview_and_venv_e_terms_agree_on_all_shared_volumes(paraview, tmp_path, shared_data):
    volumes = sorted(shared_data.glob("*.nhdr"))
    assert len(volumes) == 16
    scenes, jobs = [], []
    for path in volumes:
        spec = load_spec(REPO / "state_files" / f"{path.stem}.json")
        vol = load_volume(path)
        cams = _cameras(vol, spec)
        scenes.append((path.stem, vol, spec, cams))
        jobs.append(
            {
                "name": path.stem,
                "volume": str(path),
                "spec": json.dumps(spec_to_dict(spec)),
                "cameras": {f"{path.stem} {k}": c.to_dict() for k, c in cams.items()},
            }
        )
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    (tmp_path / "xenv.py").write_text(SCRIPT)
    cmd = [str(paraview.pvpython), str(tmp_path / "xenv.py"), str(tmp_path / "jobs.json")]
    # ParaView computes while the library computes the same scenes here (2 cores)
    proc = subprocess.Popen(
        cmd,
        env=paraview.env,
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        mine = {}
        for name, vol, spec, cams in scenes:
            curv, _ = curvature_volume(vol, spec, sigma=1.0)
            for key, cam in cams.items():
                res = analyze(vol, spec, cam, curvature=curv, build_cache=False)
                mine[f"{name} {key}"] = [
                    visibility(res, spec).E_v,
                    shape(res, spec).E_s,
                    transparency(res, spec).E_t,
                ]
        stdout, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    got = paraview.result(subprocess.CompletedProcess(cmd, proc.returncode, stdout, ""))
    # both sides on the same back end: numba, unless DVR_PERCEPTION_NO_NUMBA is set (numpy)
    assert got["numba"] == (kernels("dvr_perception.rays._numba_grid") is not None), got["numba"]
    assert set(got["E"]) == set(mine)
    bad = [
        f"{key} {term}: ParaView {theirs[i]!r}, venv {mine[key][i]!r}"
        for key, theirs in got["E"].items()
        for i, term in enumerate(TERMS)
        if abs(theirs[i] - mine[key][i]) > CROSS_ENV_ABS
    ]
    assert not bad, "\n".join(bad)
