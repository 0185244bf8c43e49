"""Tests for transfer-function tables and the VTK converters."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.export.vtk import (
    GPU_TABLE_SAMPLES,
    spec_from_vtk,
    to_vtk_property,
    to_vtk_transfer_functions,
)
from dvr_perception.structures.spec import Lighting, RenderSettings, Structure, StructureSpec
from dvr_perception.structures.transfer import (
    build_lut,
    classify,
    colour_table,
    lut_index,
    membership,
    opacity_table,
)
from dvr_perception.volume.volume import Volume

RED, BLUE = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)


@pytest.fixture
def spec2() -> StructureSpec:
    """Two touching structures: a = [0, 100] (ramps of 10), b = [100, 200] (ramps of 20)."""
    return StructureSpec(
        (
            Structure("a", 0.5, RED, range=(0, 100), edge=0.1),
            Structure("b", 1.0, BLUE, range=(100, 200), edge=0.2),
        )
    )


def test_membership_hand_values(spec2):
    a, b = spec2.structures
    got = membership([-5, 0, 5, 10, 50, 95, 100, 101], a)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, [0, 0, 0.5, 1, 1, 0.5, 0, 0])
    np.testing.assert_allclose(
        membership([100, 110, 120, 150, 190, 200], b), [0, 0.5, 1, 1, 0.5, 0]
    )


def test_membership_edge_zero_is_a_box():
    s = Structure("s", 1.0, RED, range=(10, 20), edge=0.0)
    np.testing.assert_allclose(membership([10, 10.001, 15, 19.999, 20], s), [0, 1, 1, 1, 0])


def test_membership_rejects_label_and_bad_edge():
    with pytest.raises(DVRInputError, match="label structure"):
        membership([1.0], Structure("l", 1.0, RED, label=3))
    with pytest.raises(DVRInputError, match="edge"):
        membership([1.0], Structure("e", 1.0, RED, range=(0, 1), edge=0.7))


def test_classify_keeps_shape_and_ids(spec2):
    vals = np.array([[0, 5, 50], [100, 150, 250]], dtype=np.uint8)
    ids, mem = classify(vals, spec2)
    assert ids.dtype == np.int16
    assert ids.shape == (2, 3)
    assert ids.tolist() == [[-1, 0, 0], [-1, 1, -1]]
    np.testing.assert_allclose(mem, [[0, 0.5, 1], [0, 1, 0]])


def test_classify_rejects_overlap():
    spec = StructureSpec(
        (Structure("a", 1, RED, range=(0, 60)), Structure("b", 1, BLUE, range=(50, 90)))
    )
    with pytest.raises(DVRInputError, match="overlap"):
        classify([1.0], spec)


def test_lut_uint8_full_range(spec2):
    lut = build_lut(spec2, scalar_range=(0, 255), dtype=np.uint8)
    assert lut.size == 256
    assert lut.lo == 0
    assert lut.scale == 1
    assert lut.ids[[0, 1, 50, 100, 101, 150, 199, 200, 255]].tolist() == [
        -1,
        0,
        0,
        -1,
        1,
        1,
        1,
        -1,
        -1,
    ]
    assert lut.membership[5] == pytest.approx(0.5)
    assert lut.membership[110] == pytest.approx(0.5)


def test_lut_uses_data_range_not_dtype_range(spec2):
    lut = build_lut(spec2, scalar_range=(20, 240), dtype="uint8")
    assert lut.size == 221
    assert lut.lo == 20
    assert lut.ids[0] == 0
    assert lut.ids[80] == -1
    assert lut_index([20, 20.9, 100, 300, 0], lut).tolist() == [0, 0, 80, 220, 0]


def test_lut_uint16_narrow_and_wide_ranges(spec2):
    narrow = build_lut(spec2, scalar_range=(0, 3272), dtype="<u2")
    assert narrow.size == 3273
    assert narrow.scale == 1
    wide = build_lut(spec2, scalar_range=(0, 40000), dtype=np.uint16)
    assert wide.size == 32768
    assert wide.scale == pytest.approx(32767 / 40000)
    assert wide.values[-1] == pytest.approx(40000)


def test_lut_float_matches_classify_of_entry_values(spec2):
    lut = build_lut(spec2, scalar_range=(-10.0, 250.0), dtype=np.float32)
    assert lut.size == 32768
    assert lut.values[0] == -10
    assert lut.values[-1] == pytest.approx(250)
    ids, mem = classify(lut.values, spec2)
    assert np.array_equal(ids, lut.ids)
    np.testing.assert_allclose(mem, lut.membership)
    assert lut_index([-10.0, 250.0], lut).tolist() == [0, 32767]


def test_opacity_and_color_tables(spec2):
    lut = build_lut(spec2, scalar_range=(0, 255), dtype=np.uint8)
    op = opacity_table(lut, [0.5, 0.25])
    assert op.dtype == np.float32
    assert op.shape == (256,)
    assert op[[0, 5, 50, 110, 150, 250]].tolist() == pytest.approx([0, 0.25, 0.5, 0.125, 0.25, 0])
    col = colour_table(lut, [RED, BLUE])
    assert col.shape == (256, 3)
    assert col[50].tolist() == list(RED)
    assert col[150].tolist() == list(BLUE)
    assert col[250].tolist() == [0, 0, 0]
    with pytest.raises(DVRInputError, match="opacities"):
        opacity_table(lut, [0.5])


def test_vtk_functions_reproduce_the_tables(spec2):
    ctf, otf = to_vtk_transfer_functions(spec2, opacities=[0.5, 0.25])
    for dtype, rng in (("uint8", (0, 255)), ("float32", (-3.0, 260.0))):
        lut = build_lut(spec2, scalar_range=rng, dtype=dtype)
        vtk_table = np.zeros(lut.size)
        otf.GetTable(rng[0], rng[1], lut.size, vtk_table)
        np.testing.assert_allclose(vtk_table, opacity_table(lut, [0.5, 0.25]), atol=1e-6)
    # colours stay pure up to the shared boundary, on both sides
    assert ctf.GetColor(99.0) == pytest.approx(RED)
    assert ctf.GetColor(100.5) == pytest.approx(BLUE)
    assert otf.GetValue(50) == pytest.approx(0.5)
    assert otf.GetValue(110) == pytest.approx(0.125)


def test_vtk_functions_reject_label_structures_and_bad_opacities(spec2):
    labelled = StructureSpec((*spec2.structures, Structure("l", 1.0, RED, label=2)))
    with pytest.raises(DVRInputError, match="label"):
        to_vtk_transfer_functions(labelled)
    with pytest.raises(DVRInputError, match="one per structure"):
        to_vtk_transfer_functions(spec2, opacities=[0.1])
    with pytest.raises(DVRInputError, match=r"\[0, 1\]"):
        to_vtk_transfer_functions(spec2, opacities=[0.1, 1.5])


def test_round_trip_spec_vtk_spec(spec2):
    spec = StructureSpec(
        (*spec2.structures, Structure("c", 0.3, (0.2, 0.9, 0.4), range=(220, 240), edge=0.0))
    )
    back = spec_from_vtk(*to_vtk_transfer_functions(spec), names=list(spec.names))
    assert back.names == spec.names
    for s, t in zip(spec.structures, back.structures, strict=True):
        assert t.range == pytest.approx(s.range)
        assert t.importance == pytest.approx(s.importance)
        assert t.colour == pytest.approx(s.colour)
        assert t.edge == pytest.approx(s.edge, abs=1e-6)


def test_spec_from_vtk_rejects_other_shapes():
    from dvr_perception._vtk import vtkColorTransferFunction, vtkPiecewiseFunction

    otf = vtkPiecewiseFunction()
    for x, y in ((0, 0), (10, 0.5), (20, 0.9), (30, 0)):
        otf.AddPoint(x, y)
    with pytest.raises(DVRInputError, match="trapezoid"):
        spec_from_vtk(vtkColorTransferFunction(), otf)


def test_property_settings_and_lighting_warning(spec2):
    vol = Volume(np.zeros((4, 4, 4), np.uint8), spacing=(0.5, 2.0, 1.0))
    prop = to_vtk_property(spec2, vol, shade=False)
    assert prop.GetScalarOpacityUnitDistance() == pytest.approx(0.5)
    assert prop.GetShade() == 0
    assert prop.GetInterpolationType() == 1
    assert prop.GetSpecularPower() == pytest.approx(16.0)
    spec = StructureSpec(
        spec2.structures, rendering=RenderSettings(shade=True, opacity_unit_distance=3.0)
    )
    prop = to_vtk_property(spec, vol)
    assert prop.GetShade() == 1
    assert prop.GetScalarOpacityUnitDistance() == pytest.approx(3.0)
    shiny = Structure("b", 1.0, BLUE, range=(100, 200), lighting=Lighting(specular=0.9))
    mixed = StructureSpec((spec2.structures[0], shiny))
    with pytest.warns(DVRWarning, match="per-structure lighting"):
        prop = to_vtk_property(mixed, vol)
    assert prop.GetSpecular() == pytest.approx(0.2)


def test_gpu_samples_keep_nodes_one_table_entry_apart():
    # The engine's optimised spec whose colour points 127.9962 / 128.0052 made ParaView's GPU
    # mapper ask for a 32768-texel lookup texture (more than OpenGL's 16384 on Mesa).
    spec = StructureSpec(
        (
            Structure("light", 0.2, RED, range=(90, 128), edge=0.1),
            Structure("dense", 0.2, BLUE, range=(128, 180), edge=0.1),
            Structure("inserts", 0.3, RED, range=(190, 255), edge=0.0),
        )
    )
    exact, _ = to_vtk_transfer_functions(spec)
    assert exact.EstimateMinNumberOfSamples(0.0, 255.0) > 16384
    ctf, otf = to_vtk_transfer_functions(spec, samples=GPU_TABLE_SAMPLES, scalar_range=(0, 255))
    for fn in (ctf, otf):
        assert fn.EstimateMinNumberOfSamples(0.0, 255.0) <= GPU_TABLE_SAMPLES
    # the same colours where the opacity is not ~0, the trapezoids to within the node spacing
    gap = 255.0 / GPU_TABLE_SAMPLES
    assert ctf.GetColor(127.9) == pytest.approx(RED)
    assert ctf.GetColor(128.0 + 2 * gap) == pytest.approx(BLUE)
    assert otf.GetValue(110.0) == pytest.approx(0.2)
    assert otf.GetValue(190.0 + gap) == pytest.approx(0.3)  # the edge-0 step, one entry wide
    assert otf.GetValue(190.0) == 0.0
    with pytest.raises(DVRInputError, match="samples"):
        to_vtk_transfer_functions(spec, samples=1)


@pytest.mark.parametrize(
    "name", ["GPU_TABLE_SAMPLES", "spec_from_vtk", "to_vtk_property", "to_vtk_transfer_functions"]
)
def test_the_vtk_converters_old_path_warns_and_still_works(name):
    from dvr_perception.export import vtk
    from dvr_perception.structures import transfer

    with pytest.warns(DeprecationWarning, match=rf"dvr_perception\.export\.{name}"):
        old = getattr(transfer, name)
    assert old is getattr(vtk, name)
    with pytest.raises(AttributeError):
        transfer.no_such_name  # noqa: B018


def test_colour_table_old_spelling_warns_and_still_works():
    from dvr_perception.structures import transfer

    spec = StructureSpec((Structure("a", 0.5, RED, range=(10.0, 20.0)),))
    lut = build_lut(spec, scalar_range=(0, 40), dtype=np.uint8)
    with pytest.warns(DeprecationWarning, match=r"color_table is deprecated; use .*colour_table"):
        old = transfer.color_table(lut, [RED])
    np.testing.assert_array_equal(old, colour_table(lut, [RED]))
    assert old[15].tolist() == list(RED)
