"""Tests for the ParaView preset and 3D Slicer volume-property exporters."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.vtkCommonDataModel import vtkPiecewiseFunction
from vtkmodules.vtkRenderingCore import vtkColorTransferFunction

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.export import (
    GPU_TABLE_SAMPLES,
    paraview_preset,
    save_paraview_preset,
    save_slicer_vp,
    slicer_volume_property,
    to_vtk_transfer_functions,
)
from dvr_perception.export.slicer import SLICER_VP_SCHEMA
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.structures.transfer import membership
from dvr_perception.volume.volume import Volume

RED, GREEN, BLUE = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
SAMPLES = np.linspace(-50, 450, 2001)


@pytest.fixture
def spec3() -> StructureSpec:
    """Touching a | b, a hard-edged c after a gap."""
    return StructureSpec(
        (
            Structure("a", 0.5, RED, range=(0, 100), edge=0.1),
            Structure("b", 0.9, GREEN, range=(100, 200), edge=0.25, opacity=0.3),
            Structure("c", 1.0, BLUE, range=(300, 400), edge=0.0),
        ),
        rendering=RenderSettings(shade=False, opacity_unit_distance=2.5),
    )


def _eval(ctf, otf):
    rgb = np.array([ctf.GetColor(v) for v in SAMPLES])
    op = np.array([otf.GetValue(v) for v in SAMPLES])
    return rgb, op


def _from_paraview(preset):
    ctf, otf = vtkColorTransferFunction(), vtkPiecewiseFunction()
    rgb, pts = preset["RGBPoints"], preset["Points"]
    for i in range(0, len(rgb), 4):
        ctf.AddRGBPoint(*rgb[i : i + 4])
    for i in range(0, len(pts), 4):
        otf.AddPoint(*pts[i : i + 4])
    return ctf, otf


def _from_slicer(doc):
    comp = doc["volumeProperties"][0]["components"][0]
    ctf, otf = vtkColorTransferFunction(), vtkPiecewiseFunction()
    for p in comp["rgbTransferFunction"]["points"]:
        ctf.AddRGBPoint(p["x"], *p["color"], p["midpoint"], p["sharpness"])
    for p in comp["scalarOpacity"]["points"]:
        otf.AddPoint(p["x"], p["y"], p["midpoint"], p["sharpness"])
    return ctf, otf


def _expected_opacity(spec, opacities):
    out = np.zeros_like(SAMPLES)
    for s, o in zip(spec.structures, opacities, strict=True):
        out += o * membership(SAMPLES, s).astype(np.float64)
    return out


@pytest.mark.parametrize("opacities", [None, [0.2, 0.4, 0.6]])
def test_paraview_reproduces_vtk_functions(spec3, tmp_path, opacities):
    path = save_paraview_preset(spec3, tmp_path / "tf.json", opacities=opacities)
    (preset,) = json.loads(path.read_text())
    # the nodes kept one GPU table entry apart (ParaView's lookup texture; see the module)
    want = to_vtk_transfer_functions(spec3, opacities=opacities, samples=GPU_TABLE_SAMPLES)
    want_rgb, want_op = _eval(*want)
    got_rgb, got_op = _eval(*_from_paraview(preset))
    np.testing.assert_array_equal(got_rgb, want_rgb)
    np.testing.assert_array_equal(got_op, want_op)
    # and the opacity is the documented trapezoid sum o * m(v)
    ops = opacities or [0.5, 0.3, 1.0]
    np.testing.assert_allclose(got_op, _expected_opacity(spec3, ops), atol=1e-5)
    # colour inside each plateau is the structure's colour
    for v, col in ((50, RED), (150, GREEN), (350, BLUE)):
        np.testing.assert_allclose(_from_paraview(preset)[0].GetColor(v), col)


def test_paraview_keys_and_layout(spec3, tmp_path):
    path = save_paraview_preset(spec3, tmp_path / "my map.json")
    doc = json.loads(path.read_text())
    assert isinstance(doc, list)
    assert len(doc) == 1
    preset = doc[0]
    assert {"Name", "ColorSpace", "RGBPoints", "Points"} <= set(preset)
    assert preset["Name"] == "my map"
    assert preset["ColorSpace"] == "RGB"
    assert len(preset["RGBPoints"]) % 4 == 0
    assert len(preset["Points"]) % 4 == 0
    # touching structures share the zero point at 100: 4 + 3 + 4 opacity nodes
    assert len(preset["Points"]) == 11 * 4
    xs = preset["Points"][0::4]
    assert xs == sorted(xs)
    assert len(set(xs)) == len(xs)
    assert set(preset["Points"][2::4]) == {0.5}
    assert set(preset["Points"][3::4]) == {0.0}
    assert paraview_preset(spec3, name="x")["Name"] == "x"


def test_slicer_reproduces_vtk_functions(spec3, tmp_path):
    path = save_slicer_vp(spec3, tmp_path / "tf.vp.json")
    doc = json.loads(path.read_text())
    want_rgb, want_op = _eval(*to_vtk_transfer_functions(spec3))
    got_rgb, got_op = _eval(*_from_slicer(doc))
    np.testing.assert_array_equal(got_rgb, want_rgb)
    np.testing.assert_array_equal(got_op, want_op)
    np.testing.assert_allclose(got_op, _expected_opacity(spec3, [0.5, 0.3, 1.0]), atol=1e-5)


def test_slicer_keys(spec3):
    doc = slicer_volume_property(spec3)
    assert doc["@schema"] == SLICER_VP_SCHEMA
    (vp,) = doc["volumeProperties"]
    assert vp["interpolationType"] == "linear"
    assert vp["effectiveRange"] == [0.0, 400.0]
    (comp,) = vp["components"]
    for key in ("shade", "lighting", "scalarOpacity", "gradientOpacity", "rgbTransferFunction"):
        assert key in comp
    assert comp["shade"] is False
    assert comp["scalarOpacityUnitDistance"] == 2.5
    assert comp["lighting"] == {
        "diffuse": 0.8,
        "ambient": 0.2,
        "specular": 0.2,
        "specularPower": 16.0,
    }
    for p in comp["scalarOpacity"]["points"]:
        assert set(p) == {"x", "y", "midpoint", "sharpness"}
    for p in comp["rgbTransferFunction"]["points"]:
        assert set(p) == {"x", "color", "midpoint", "sharpness"}
        assert len(p["color"]) == 3
    assert doc["dvr_perception"]["notes"] == []


def test_slicer_volume_sets_range_and_unit_distance():
    spec = StructureSpec((Structure("a", 0.5, RED, range=(10, 20)),))
    data = np.zeros((4, 4, 4), np.int16)
    data[0, 0, 0], data[-1, -1, -1] = -100, 900
    vol = Volume(data, spacing=(0.7, 0.5, 2.0))
    comp = slicer_volume_property(spec, vol)["volumeProperties"][0]
    assert comp["effectiveRange"] == [-100.0, 900.0]
    assert comp["components"][0]["scalarOpacityUnitDistance"] == 0.5
    doc = slicer_volume_property(spec)
    assert doc["volumeProperties"][0]["components"][0]["scalarOpacityUnitDistance"] == 1.0
    assert "scalarOpacityUnitDistance" in doc["dvr_perception"]["notes"][0]


def test_slicer_mixed_lighting_warns_and_notes():
    spec = StructureSpec(
        (
            Structure("a", 0.5, RED, range=(0, 10), lighting=Lighting(ambient=0.5)),
            Structure("b", 0.5, BLUE, range=(10, 20)),
        )
    )
    with pytest.warns(DVRWarning, match="different lighting"):
        doc = slicer_volume_property(spec)
    comp = doc["volumeProperties"][0]["components"][0]
    assert comp["lighting"]["ambient"] == 0.5
    assert any("'a'" in n for n in doc["dvr_perception"]["notes"])


@pytest.fixture
def label_spec() -> StructureSpec:
    return StructureSpec(
        (Structure("a", 0.5, RED, range=(0, 10)), Structure("organ", 0.5, BLUE, label=3)),
        labels_file="labels.nrrd",
    )


@pytest.mark.parametrize("save", [save_paraview_preset, save_slicer_vp])
def test_label_structures_are_refused(label_spec, tmp_path, save):
    target = tmp_path / "out.json"
    with pytest.raises(DVRInputError, match=r"'organ'.*label structure"):
        save(label_spec, target)
    assert not target.exists()


def test_bad_arguments(spec3):
    with pytest.raises(DVRInputError, match="name"):
        paraview_preset(spec3, name="  ")
    with pytest.raises(DVRInputError, match="opacities"):
        paraview_preset(spec3, opacities=[0.1, 0.2])
    with pytest.raises(DVRInputError, match="spec"):
        slicer_volume_property({"structures": []})


@pytest.mark.parametrize("save", [save_paraview_preset, save_slicer_vp])
def test_writes_are_atomic(spec3, tmp_path, monkeypatch, save):
    target = tmp_path / "out.json"
    target.write_text("previous")
    real = Path.write_text

    def half_then_fail(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError("disk full")

    monkeypatch.setattr(Path, "write_text", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        save(spec3, target)
    monkeypatch.undo()
    assert target.read_text() == "previous"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def _vtk_node_values(ctf, otf):
    """The nodes VTK holds, read back with ``GetNodeValue``."""
    color, opacity = [], []
    for i in range(ctf.GetSize()):
        node = [0.0] * 6
        ctf.GetNodeValue(i, node)
        color.append(node)
    for i in range(otf.GetSize()):
        node = [0.0] * 4
        otf.GetNodeValue(i, node)
        opacity.append(node)
    return color, opacity


def _specs_to_export():
    """spec3 as made here, the phantom's and every repository preset of range structures."""
    from dvr_perception.structures.io import load_spec
    from dvr_perception.structures.phantom import make_phantom

    specs = [make_phantom(size=16)[1]]
    for path in sorted((Path(__file__).parents[2] / "state_files").glob("*.json")):
        spec = load_spec(path)
        if all(s.range is not None for s in spec.structures):
            specs.append(spec)
    return specs


def test_nodes_without_vtk_equal_vtks_nodes(spec3):
    """The exporters' nodes (built without VTK) are VTK's own, bit for bit.

    Touching structures (spec3's a | b share x = 100: VTK replaces the node there), the GPU
    table spacing (triangles, merged zeros) and a wide scalar range are all covered; the
    exporters write these lists, so ParaView and Slicer get VTK's functions.
    """
    from dvr_perception.export._common import transfer_nodes

    specs = [spec3, *_specs_to_export()]
    assert len(specs) >= 10
    cases = 0
    for spec in specs:
        ops = np.linspace(0.05, 1.0, len(spec.structures))
        for kwargs in ({}, {"opacities": ops}, {"samples": GPU_TABLE_SAMPLES},
                       {"samples": 64, "scalar_range": (-1000.0, 5000.0)},
                       {"samples": 7, "opacities": ops}):  # fmt: skip
            got = transfer_nodes(spec, kwargs.get("opacities"), kwargs.get("samples"),
                                 kwargs.get("scalar_range"))  # fmt: skip
            want = _vtk_node_values(*to_vtk_transfer_functions(spec, **kwargs))
            assert got == want, (spec.names, kwargs)
            cases += 1
    assert cases == 5 * len(specs)
    # spec3: VTK kept one node at the shared x = 100 (4 + 3 + 4 opacity nodes)
    assert len(transfer_nodes(spec3, None)[1]) == 11


def test_writing_the_presets_imports_no_vtk(tmp_path):
    code = (
        "import sys\n"
        "from dvr_perception.export import save_paraview_preset, save_slicer_vp\n"
        "from dvr_perception.structures.phantom import make_phantom\n"
        "vol, spec = make_phantom(size=16)\n"
        f"save_paraview_preset(spec, {str(tmp_path / 'p.json')!r})\n"
        f"save_slicer_vp(spec, {str(tmp_path / 's.vp.json')!r}, vol)\n"
        "print(sorted({m.split('.')[0] for m in sys.modules if m.startswith('vtk')}))\n"
    )
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-W", "ignore", "-c", code], capture_output=True,
                          text=True, check=False, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "[]"
    assert json.loads((tmp_path / "p.json").read_text())[0]["Points"]
