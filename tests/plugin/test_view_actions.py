"""*Optimise this view* applies the result to the volume you see (issue 19, deliveries 1-3).

``view_actions_scene.py`` opens neghip in a 3-D view, sets a camera and runs
``dvr_view.optimise_this_view`` (the *DVR Optimise View* macro) -- in the real ``paraview``
GUI under Xvfb, and in pvpython connected to a ``pvserver`` on 127.0.0.1.  Checked against the
library: the filter used the view's camera; the view's volume representation carries the
optimised spec's transfer functions (the nodes of ``paraview_preset`` for the spec), its
material, shading and opacity unit distance; the preset was imported; ParaView's rendering is
within SSIM 0.9 of the engine's (shaded in the GUI, unshaded on the server); the quality maps
are in 2-D views beside the 3-D view with a legend each and the table in a spreadsheet; the
output is not shown in the 3-D view; *Undo* restores the transfer functions; ParaView printed
no VTK warning.  ``DVR_DOC_IMAGES=DIR`` copies the GUI run's screenshots into ``DIR``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dvr_perception.cli.pvbatch import find_paraview
from dvr_perception.errors import DVRInputError
from dvr_perception.export import paraview_preset
from dvr_perception.structures.io import load_spec, spec_from_dict
from tests.plugin.conftest import _missing, assert_no_vtk_messages
from tests.plugin.test_pvserver import _free_port, _listening, _reader, _stop

REPO = Path(__file__).resolve().parents[2]
SCENE = Path(__file__).with_name("view_actions_scene.py")
SPEC = REPO / "state_files" / "neghip.json"
SSIM_MIN = 0.9
#: The GUI test's light direction (camera coordinates, unit): 25 degrees off the headlight.
LIGHT = [0.33809, 0.25357, 0.90631]


def _scene_env(paraview, display, shared_data, out, spec, port=None):
    env = dict(paraview.env, DISPLAY=display, DVR_REPO=str(REPO), DVR_OUT=str(out))
    # ParaView keeps imported presets in the user's settings: a private home for the run
    home = out / "home"
    (home / ".config").mkdir(parents=True, exist_ok=True)
    env.update(HOME=str(home), XDG_CONFIG_HOME=str(home / ".config"))
    env.update(DVR_VOLUME=str(shared_data / "neghip.nhdr"), DVR_SPEC=str(spec))
    if port is not None:
        env["DVR_SERVER_PORT"] = str(port)
    return env


def _image(path: Path) -> np.ndarray:
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOImage import vtkPNGReader

    assert path.is_file(), path
    reader = vtkPNGReader()
    reader.SetFileName(str(path))
    reader.Update()
    img = reader.GetOutput()
    w, h, _ = img.GetDimensions()
    return vtk_to_numpy(img.GetPointData().GetScalars()).reshape(h, w, -1)[..., :3]


def _engine_ssim(got: dict, out: Path, volume_path: Path) -> float:
    """SSIM of ParaView's capture vs the library's image of the optimised spec (this venv)."""
    from dvr_perception.rays.camera import Camera
    from dvr_perception.rays.curvature import curvature_volume
    from dvr_perception.rays.engine import analyze
    from dvr_perception.rays.vtk_reference import compare_images
    from dvr_perception.volume import load_volume

    spec = spec_from_dict(got["spec"], source="result")
    width, height = got["filter_size"]
    camera = Camera.from_dict(dict(got["filter_camera"], width=width, height=height))
    volume = load_volume(volume_path)
    curvature, _ = curvature_volume(volume, spec)
    rgba = np.asarray(analyze(volume, spec, camera, curvature=curvature).rgba, float)
    engine = rgba[..., :3] + (1.0 - rgba[..., 3:]) * np.asarray(spec.background, float)
    capture = _image(out / "paraview_capture.png")[::-1] / 255.0  # VTK rows go up
    return compare_images(capture, np.clip(engine, 0.0, 1.0))["ssim"]


def _check(out: Path, text: str, spec_path: Path) -> dict:
    """The assertions both runs share; returns the scene's result."""
    assert "@@DONE@@" in text, text
    print("".join(f"{ln} " for ln in text.splitlines() if ln.startswith("@@T ")))  # timings
    assert_no_vtk_messages(text)
    got = json.loads((out / "result.json").read_text())
    given = load_spec(spec_path)
    # the camera the filter used is the view's
    for key in ("position", "focal_point", "view_up"):
        assert got["filter_camera"][key] == pytest.approx(got["view_camera"][key], abs=1e-9)
    assert got["filter_camera"]["view_angle"] == pytest.approx(got["view_camera"]["view_angle"])
    assert got["use_spec_view"] == 0
    assert got["filter_size"][1] == 32
    # the maps were opened before the camera was copied: the image has the aspect ratio the
    # 3-D view has beside them (in the GUI the split halves the view's width at once)
    vw, vh = got["optimise_view_size"]
    assert got["filter_size"][0] == round(32 * vw / vh)
    # the view's volume representation carries the optimised spec's transfer functions
    spec = spec_from_dict(got["spec"], source="result")
    assert [s.render_opacity for s in spec.structures] != [
        s.render_opacity for s in given.structures
    ]
    preset = paraview_preset(spec, name=got["preset"], scalar_range=tuple(got["data_range"]))
    assert got["RGBPoints"] == pytest.approx(preset["RGBPoints"], abs=1e-9)
    assert got["Points"] == pytest.approx(preset["Points"], abs=1e-9)
    assert got["RGBPoints"] != got["before"]["RGBPoints"]
    assert got["lut_range_mode"] == "Never"
    saved = got["preset_saved"][0]  # the preset file as the action wrote it
    assert saved["Name"] == got["preset"]
    assert got["preset_known"]
    assert saved["Points"] == pytest.approx(preset["Points"], abs=1e-9)
    top = max(spec.structures, key=lambda s: s.importance).lighting
    material = [top.ambient, top.diffuse, top.specular, top.specular_power]
    assert got["material"] == pytest.approx(material)
    assert got["shade"] == int(spec.rendering.shade)
    assert got["unit_distance"] == pytest.approx(1.0)  # neghip's spacing; the spec sets none
    assert got["background"] == pytest.approx(list(spec.background))
    # ParaView's rendering vs the engine's image, reported in the output's field data
    assert got["ssim_field"] == pytest.approx(got["ssim"])
    assert got["ssim"] >= SSIM_MIN, got["ssim"]
    # ... and recomputed here from ParaView's capture and the library's image in this venv
    got["ssim_venv"] = _engine_ssim(got, out, Path(got["volume"]))
    assert got["ssim_venv"] == pytest.approx(got["ssim"], abs=2e-3)
    # the maps beside the 3-D view (never in it), a legend each; the table in a spreadsheet
    assert not got["output_in_3d_view"]
    assert got["preferred_view"] == "SpreadSheetView"  # a plain Apply: a view of its own
    assert len(got["quality"]) == 3
    for title, q in got["quality"].items():
        assert q == {"in_layout": True, "visible": True, "array": q["array"], "bar": True,
                     "bar_title": title, "2d": True}, title  # fmt: skip
        assert q["array"].endswith("_deviation")
    assert got["table"] == {"in_layout": True, "field_data": True, "visible": True}
    assert len(got["why"]) == 3
    assert all("->" in line for line in got["why"])
    # Undo: the transfer functions before the action, and nothing more to undo
    assert got["undone"]
    assert not got["undo_again"]
    assert got["after_undo"] == got["before"]
    # the screenshots show something: the volume on the spec's black background, a map
    shot = _image(out / "view_3d.png")
    assert 0.05 < float((shot.max(axis=-1) > 20).mean()) < 0.9
    assert len(np.unique(_image(out / "quality_map.png").reshape(-1, 3), axis=0)) > 16
    return got


def _assert_band_lens(got: dict) -> None:
    """The lens is the rubber band (display pixels, y up) scaled to the filter's image."""
    vw, vh = got["view_size"]
    w, h = got["band_size"]
    assert w == round(h * vw / vh)
    x0, y0, x1, y1 = got["rubber_band"]
    expected = [x0 * w / vw, (vh - y1) * h / vh, x1 * w / vw, (vh - y0) * h / vh]
    assert got["band_lens"] == pytest.approx(expected, abs=1.0), (got["band_lens"], expected)
    print(f"rubber band {x0, y0, x1, y1} in the {vw} x {vh} view -> lens "
          f"{tuple(got['band_lens'])} of the {w} x {h} image (scaled {expected})")  # fmt: skip


def test_optimise_this_view_in_the_gui(paraview, display, shared_data, tmp_path):
    gui = shutil.which("paraview")
    if gui is None:
        _missing("the ParaView GUI (paraview) is not installed (make paraview-system)")
    spec = json.loads(SPEC.read_text())
    spec["rendering"]["light_direction"] = LIGHT  # an optimised light off the headlight
    spec_path = tmp_path / "neghip_light.json"
    spec_path.write_text(json.dumps(spec))
    env = _scene_env(paraview, display, shared_data, tmp_path, spec_path)
    proc = paraview.call(
        [gui, "--dr", f"--script={SCENE}", "--exit"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=300,
        check=False,
        cwd=tmp_path,
    )
    got = _check(tmp_path, proc.stdout, spec_path)
    assert not got["remote"]
    # the light: the kit off, one light of the action's, the better of the two tried
    assert got["spec"]["rendering"]["light_direction"] == pytest.approx(LIGHT, abs=1e-4)
    tried = got["ssim_by_light"]
    assert set(tried) == {"view's lights", "headlight", "optimised direction"}
    assert got["ssim"] == pytest.approx(max(tried["headlight"], tried["optimised direction"]))
    assert got["ssim"] == pytest.approx(tried[got["light"]])
    assert got["lights"]["use_light"] == 0
    (light,) = got["lights"]["extra"]
    assert light["Name"] == "DVR Perception light"
    assert light["Enable"] == 1
    assert light["Intensity"] == pytest.approx(1.0)
    if got["light"] == "headlight":
        assert light["Coords"] == "Headlight"
    else:
        assert light["Coords"] == "Camera"
        assert light["Position"] == pytest.approx(LIGHT, abs=1e-4)
        assert light["FocalPoint"] == pytest.approx([0.0, 0.0, 0.0])
    assert got["lights_after_undo"] == {"use_light": 1, "extra": []}  # Undo: the kit again
    assert got["macros"] == [
        "DVR_Measure_View", "DVR_Optimise_View", "DVR_Refine_Region", "DVR_Undo",
        "DVR_Use_View_Camera",
    ]  # fmt: skip
    assert got["shade"] == 1  # neghip's spec is shaded: the shaded SSIM
    # a plain Apply in the GUI follows the 3-D view's camera (FollowView)
    assert got["plain_apply"]["plain"] == pytest.approx(got["plain_apply"]["given"], abs=1e-12)
    # Refine region from the rubber band drawn in the 3-D view: its pixels, in the filter's
    assert got["region_from"] == "3d view"
    _assert_band_lens(got)
    assert got["region_property"] == "rect,{},{},{},{}".format(*got["band_lens"])
    assert got["refined_lens"] == got["region_property"]
    assert got["lens_E"]["E"] <= got["lens_initial_E"]["E"] + 1e-9  # the lens improved
    assert got["lens_initial_E"]["E"] != pytest.approx(got["refined_initial_E"]["E"], abs=1e-6)
    print(f"lens E {got['lens_initial_E']['E']:.4f} -> {got['lens_E']['E']:.4f}; whole image "
          f"{got['refined_initial_E']['E']:.4f} -> {got['refined_E']['E']:.4f}")  # fmt: skip
    print(f"GUI, shaded: SSIM {got['ssim']:.4f} (venv {got['ssim_venv']:.4f}), light "
          f"{got['light']}; by light {tried}")  # fmt: skip
    docs = os.environ.get("DVR_DOC_IMAGES")
    if docs:
        for name in ("view_3d.png", "quality_map.png", "layout.png"):  # the scene saw the env
            shutil.copyfile(tmp_path / name, Path(docs) / f"paraview_optimise_view_{name}")


def test_optimise_this_view_on_pvserver(paraview, display, loopback_shim, shared_data, tmp_path):
    import queue
    import threading
    import time

    try:
        pvserver = find_paraview("pvserver")
    except DVRInputError as exc:
        pytest.fail(f"pvpython is installed but pvserver is not: {exc}")
    spec = json.loads(SPEC.read_text())
    spec["rendering"]["shade"] = False
    spec_path = tmp_path / "neghip_unshaded.json"
    spec_path.write_text(json.dumps(spec))
    port = _free_port()
    env = _scene_env(paraview, display, shared_data, tmp_path, spec_path, port)
    server_env = dict(env, LD_PRELOAD=str(loopback_shim))
    for key in ("DVR_SERVER_PORT", "DVR_OUT"):
        server_env.pop(key)
    cmd = [str(pvserver), f"--server-port={port}", "--hostname=localhost", "--timeout=5"]
    server = subprocess.Popen(cmd, env=server_env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, cwd=tmp_path)  # fmt: skip
    lines: queue.Queue = queue.Queue()
    pump = threading.Thread(target=_reader, args=(server.stdout, lines), daemon=True)
    pump.start()
    log: list[str] = []
    try:
        deadline = time.monotonic() + 60
        while not any("Accepting connection" in ln for ln in log):
            assert time.monotonic() < deadline, f"pvserver did not start:\n{''.join(log)}"
            try:
                line = lines.get(timeout=1)
            except queue.Empty:
                continue
            assert line is not None, f"pvserver exited ({server.poll()}):\n{''.join(log)}"
            log.append(line)
        sockets = _listening(server.pid)
        assert all(a in ("127.0.0.1", "::1") for a, _ in sockets), sockets
        client = paraview.call(
            [str(paraview.pvpython), str(SCENE)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=300,
            check=False,
            cwd=tmp_path,
        )
    finally:
        _stop(server)
        pump.join(timeout=10)
        server.stdout.close()
    while not lines.empty():
        line = lines.get()
        if line is not None:
            log.append(line)
    assert client.returncode == 0, client.stdout
    got = _check(tmp_path, client.stdout, spec_path)
    assert_no_vtk_messages("".join(log))
    assert got["remote"], "the scene did not run connected to the pvserver"
    # a plain Apply on pvserver: the spec's view (the server cannot see the client's view),
    # said once in the server's output
    assert got["plain_apply"]["plain"] != pytest.approx(got["plain_apply"]["given"], abs=1e-6)
    told = [ln for ln in log if "on pvserver takes the spec's view" in ln]
    assert len(told) == 1, "".join(log)
    assert got["shade"] == 0
    assert got["light"] is None  # unshaded: no light acts, the view's lights stay
    assert got["lights"] == got["lights_after_undo"] == {"use_light": 1, "extra": []}
    # Measure this view: the same camera; Refine region: the selected pixels' bounding box
    for key in ("position", "focal_point", "view_up"):
        assert got["measure_camera"][key] == pytest.approx(got["view_camera"][key], abs=1e-9)
    assert all(0.0 <= got["measured"][k] < 10.0 for k in ("E_v", "E_s", "E_t"))
    height = got["filter_size"][1]
    assert got["region"] == [12, height - 20, 30, height - 10]  # rows 10-19 up, x 12-29
    assert got["region_property"] == f"rect,12,{height - 20},30,{height - 10}"
    assert got["region_from"] == "quality map"
    assert got["refined_lens"] == got["region_property"]
    assert got["refined_E"]["E"] != pytest.approx(got["E"]["E"], abs=1e-9)
    # a rubber band in the 3-D view read back through the server; no selection: one error
    _assert_band_lens(got)
    assert "select a region first" in got["no_selection_error"]
    print(f"pvserver, unshaded: SSIM {got['ssim']:.4f} (venv {got['ssim_venv']:.4f})")
