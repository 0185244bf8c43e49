"""Several MPI ranks: ``mpiexec -n 2 pvbatch`` gives the serial (library) numbers, once.

ParaView asks each rank for one piece of every output and its NRRD reader (vtkPNrrdReader)
then reads one slab of the volume per rank.  The plugin's filters ask for the whole volume as
one piece on every rank (so the reader, which may read collectively, runs on all ranks alike),
compute on piece 0 (rank 0) only and leave the other pieces empty.  Without that each rank
measured its own slab and rank 0's (wrong) numbers came back.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from dvr_perception.cli.pvbatch import virtual_display
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import load_spec
from dvr_perception.volume import load_volume
from tests.plugin.conftest import CROSS_ENV_ABS

REPO = Path(__file__).resolve().parents[2]
PLUGIN = REPO / "dvr_perception" / "paraview" / "dvr_perception_plugin.py"
SPEC = REPO / "state_files" / "neghip.json"
MARK = "@@RESULT@@ "  # must match conftest.MARK
SIZE = 32
RANKS = 2

SCRIPT = f"""
import json, sys
from paraview.simple import *
from paraview.modules.vtkRemotingCore import vtkProcessModule
LoadPlugin({str(PLUGIN)!r}, ns=globals())
reader = OpenDataFile(sys.argv[1])
reader.UpdatePipeline()  # the usual split first: one slab per rank
slabs = reader.GetDataInformation().GetNumberOfPoints()
layers = StructuralLayers(Input=reader, SpecFile={str(SPEC)!r})
layers.UpdatePipeline()
pm = PerceptionMeasures(Input=reader, SpecFile={str(SPEC)!r}, Width={SIZE}, Height={SIZE})
pm.UpdatePipeline()
image = servermanager.Fetch(pm)
fd = image.GetFieldData()
print({MARK!r} + json.dumps({{
    "ranks": vtkProcessModule.GetProcessModule().GetNumberOfLocalPartitions(),
    "slab_points": slabs,
    "layers_points": layers.GetDataInformation().GetNumberOfPoints(),
    "points": pm.GetDataInformation().GetNumberOfPoints(),
    "E_v_range": list(pm.FieldData["E_v"].GetRange()),
    "E": {{k: fd.GetArray(k).GetValue(0) for k in ("E_v", "E_s", "E_t")}},
    "dims": list(image.GetDimensions()),
}}), flush=True)
"""


def test_filters_under_mpiexec_compute_once_on_the_whole_volume(paraview, tmp_path, shared_data):
    mpiexec = shutil.which("mpiexec")
    if mpiexec is None:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail("required under CI=true: mpiexec (openmpi-bin, recommended by paraview)")
        pytest.skip("no mpiexec (apt-get install openmpi-bin)")
    volume = shared_data / "neghip.nhdr"
    script = tmp_path / "mpi_measures.py"
    script.write_text(SCRIPT, encoding="utf-8")
    version = subprocess.run([mpiexec, "--version"], capture_output=True, text=True).stdout
    extra = ["--oversubscribe"] if ("Open MPI" in version or "OpenRTE" in version) else []
    env = dict(paraview.env, OMPI_MCA_mpi_yield_when_idle="1")
    if os.geteuid() == 0:  # Open MPI refuses root unless told (containers, CI images)
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    cmd = [mpiexec, "-n", str(RANKS), *extra, str(paraview.pvbatch), str(script), str(volume)]
    with virtual_display() as display:
        proc = paraview.call(
            cmd,
            env=dict(env, DISPLAY=display),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=600,
            check=False,
            cwd=tmp_path,
        )
    got = paraview.result(proc)
    assert got["ranks"] == RANKS
    n = 64**3
    assert n < got["slab_points"] < 2 * n  # the reader alone: slabs (+ one shared slice)
    # each filter's output exists once: the whole volume / one image, on rank 0
    assert got["layers_points"] == n
    assert got["points"] == SIZE * SIZE
    assert got["dims"] == [SIZE, SIZE, 1]

    vol, spec = load_volume(volume), load_spec(SPEC)
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE, height=SIZE)
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    result = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    expected = {
        "E_v": visibility(result, spec).E_v,
        "E_s": shape(result, spec).E_s,
        "E_t": transparency(result, spec).E_t,
    }
    for k, value in expected.items():
        assert got["E"][k] == pytest.approx(value, abs=CROSS_ENV_ABS), k
    # the data information over all ranks holds that one value (not a slab's next to it)
    assert got["E_v_range"] == pytest.approx([expected["E_v"]] * 2, abs=CROSS_ENV_ABS)
