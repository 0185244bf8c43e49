"""3D Slicer segmentations (``.seg.nrrd``) as structures: spec, geometry, CLI, export, bad files."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from dvr_perception.cli import main
from dvr_perception.errors import DVRInputError
from dvr_perception.export import slicer_volume_property
from dvr_perception.structures.io import attach_labels, load_spec, save_spec
from dvr_perception.structures.slicer import (
    default_importances,
    is_segmentation,
    read_segments,
    segmentation_labels,
    spec_from_segmentation,
    write_segmentation,
)
from dvr_perception.volume.io import load_volume, save_volume
from dvr_perception.volume.volume import Volume

N = 24
SPACING = (1.0, 1.0, 1.5)
ORIGIN = (-10.0, 5.0, 2.0)
SEGMENTS = [
    {"name": "Body wall", "color": (0.9, 0.75, 0.6), "label": 1, "id": "body"},
    {"name": "Liver", "color": (0.6, 0.2, 0.15), "label": 5, "id": "liver"},
    {"name": "Tumor \u00e9", "color": (0.1, 0.9, 0.2), "label": 7, "id": "tumor"},
]
NAMES = [s["name"] for s in SEGMENTS]


def _phantom():
    """24³ CT-like volume: a body box, a sphere inside it and a small sphere in the sphere."""
    z, y, x = np.mgrid[:N, :N, :N].astype(float)
    r_big = np.sqrt((x - 12) ** 2 + (y - 12) ** 2 + (z - 12) ** 2)
    r_small = np.sqrt((x - 13) ** 2 + (y - 12) ** 2 + (z - 11) ** 2)
    labels = np.zeros((N, N, N), np.uint8)
    labels[3:21, 3:21, 3:21] = 1
    labels[r_big <= 7] = 5
    labels[r_small <= 3] = 7
    data = np.choose(np.searchsorted([0, 1, 5, 7], labels), [10, 80, 150, 220]).astype(np.int16)
    return data, labels


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("seg")
    data, labels = _phantom()
    save_volume(Volume(data, spacing=SPACING, origin=ORIGIN), d / "ct.nrrd")
    write_segmentation(d / "organs.seg.nrrd", labels, SEGMENTS, spacing=SPACING, origin=ORIGIN)
    write_segmentation(
        d / "raw.seg.nrrd", labels, SEGMENTS, spacing=SPACING, origin=ORIGIN, encoding="raw"
    )
    return d, labels


def _main(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("name", ["organs.seg.nrrd", "raw.seg.nrrd"])
def test_spec_has_the_segments_names_colours_and_labels(files, name):
    d, labels = files
    assert is_segmentation(d / name)
    spec = load_spec(d / name)
    assert list(spec.names) == NAMES
    assert [s.label for s in spec.structures] == [1, 5, 7]
    assert [s.colour for s in spec.structures] == [s["color"] for s in SEGMENTS]
    assert all(s.range is None for s in spec.structures)
    # default rule: the smallest segment (the tumour) is the most important, the body the least
    imp = [s.importance for s in spec.structures]
    assert imp == [0.15, 0.5, 0.85]
    vol = attach_labels(load_volume(d / "ct.nrrd"), spec)
    assert np.array_equal(vol.labels, labels)


def test_default_importance_rule(tmp_path):
    assert default_importances([300, 20, 20, 1]) == [0.15, 0.5, 0.5, 0.85]
    assert default_importances([7]) == [0.5]
    p = write_segmentation(tmp_path / "a.seg.nrrd", _phantom()[1], SEGMENTS)
    spec = spec_from_segmentation(p, importance=0.4)
    assert [s.importance for s in spec.structures] == [0.4] * 3


def test_saved_spec_is_editable_and_reloads(files, tmp_path):
    d, labels = files
    spec = load_spec(d / "organs.seg.nrrd")
    save_spec(spec, tmp_path / "spec.json")
    doc = json.loads((tmp_path / "spec.json").read_text(encoding="utf-8"))
    assert [s["name"] for s in doc["structures"]] == NAMES
    assert doc["labels"].endswith("organs.seg.nrrd")
    doc["structures"][0]["importance"] = 0.05
    (tmp_path / "spec.json").write_text(json.dumps(doc), encoding="utf-8")
    again = load_spec(tmp_path / "spec.json")
    assert again.structures[0].importance == 0.05
    vol = attach_labels(load_volume(d / "ct.nrrd"), again)
    assert np.array_equal(vol.labels, labels)


@pytest.mark.parametrize("y_sign", [1.0, -1.0])
def test_cropped_segmentation_is_placed_by_its_origin(files, tmp_path, y_sign):
    d, labels = files
    # Slicer writes a segmentation cropped to its segments' extent: the origin moves by the
    # offset along each (signed) axis direction; LPS files often have a negative y direction
    crop = labels[2:22, 3:21, 3:21]  # z 2.., y 3.., x 3..
    spacing = (SPACING[0], y_sign * SPACING[1], SPACING[2])
    origin = (ORIGIN[0] + 3 * spacing[0], ORIGIN[1] + 3 * spacing[1], ORIGIN[2] + 2 * spacing[2])
    p = write_segmentation(
        tmp_path / "crop.seg.nrrd", crop, SEGMENTS, spacing=spacing, origin=origin
    )
    ct = d / "ct.nrrd"
    if y_sign < 0:  # the CT stored with the same negative y direction as its segmentation
        ct = tmp_path / "ct_neg.nrrd"
        head, sep, body = (d / "ct.nrrd").read_bytes().partition(b"\n\n")
        ct.write_bytes(head.replace(b"(0.0,1.0,0.0)", b"(0.0,-1.0,0.0)") + sep + body)
    vol = load_volume(ct)
    # loaded in canonical LPS order: a negative y direction flips the rows of both grids
    expected = labels if y_sign > 0 else labels[:, ::-1]
    assert np.array_equal(vol.data, _phantom()[0] if y_sign > 0 else _phantom()[0][:, ::-1])
    assert np.array_equal(segmentation_labels(p, vol), expected)


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"spacing": (1.0, 1.0, 1.0)}, r"voxel spacing .* differs from the volume's"),
        ({"origin": (ORIGIN[0] + 0.5, ORIGIN[1], ORIGIN[2])}, r"origin .* not on the volume's"),
        ({"origin": (ORIGIN[0] + 20, ORIGIN[1], ORIGIN[2])}, r"segment voxels lie outside"),
        ({"origin": (ORIGIN[0], ORIGIN[1], 1e15)}, r"segment voxels lie outside"),
    ],
)
def test_geometry_mismatch_is_one_clear_error(files, tmp_path, kw, message):
    d, labels = files
    args = {"spacing": SPACING, "origin": ORIGIN, **kw}
    p = write_segmentation(tmp_path / "other.seg.nrrd", labels, SEGMENTS, **args)
    with pytest.raises(DVRInputError, match=message) as info:
        segmentation_labels(p, load_volume(d / "ct.nrrd"))
    assert "other.seg.nrrd" in str(info.value)
    code, _, err = _main(["measure", str(d / "ct.nrrd"), "--structures", str(p), "--size", "8"])
    assert code == 2
    assert "other.seg.nrrd" in err
    assert "Traceback" not in err


def test_measure_and_save_spec_through_the_cli(files, tmp_path):
    d, _ = files
    saved = tmp_path / "organs.json"
    argv = ["measure", str(d / "ct.nrrd"), "--structures", str(d / "organs.seg.nrrd")]
    code, out, err = _main([*argv, "--size", "32", "--save-spec", str(saved), "--json"])
    assert code == 0, err
    report = json.loads(out)
    assert list(report["structures"]) == NAMES
    assert report["spec"].endswith("organs.seg.nrrd")
    assert sum(s["visible_share"] for s in report["structures"].values()) > 0.5
    assert [s["name"] for s in json.loads(saved.read_text(encoding="utf-8"))["structures"]] == NAMES


def test_optimize_keeps_names_and_colours_in_outputs_and_slicer_export(files, tmp_path):
    d, _ = files
    out = tmp_path / "opt"
    argv = ["optimize", str(d / "ct.nrrd"), "--structures", str(d / "organs.seg.nrrd")]
    argv += ["--size", "24", "--resolution", "16", "--stages", "opacity", "--max-iter", "1"]
    code, stdout, err = _main([*argv, "--out", str(out), "--json"])
    assert code == 0, err
    report = json.loads(stdout)
    assert list(report["final"]["structures"]) == NAMES
    spec = json.loads((out / "optimized_spec.json").read_text(encoding="utf-8"))
    assert [(s["name"], s["label"], s["colour"]) for s in spec["structures"]] == [
        (s["name"], s["label"], list(s["color"])) for s in SEGMENTS
    ]
    assert load_spec(out / "optimized_spec.json").names == tuple(NAMES)  # labels path resolves
    vp = json.loads((out / "slicer.vp.json").read_text(encoding="utf-8"))
    segments = vp["dvr_perception"]["segments"]
    assert [s["name"] for s in segments] == NAMES
    assert [s["color"] for s in segments] == [list(s["color"]) for s in SEGMENTS]
    assert [s["opacity"] for s in segments] == [s.get("opacity") for s in spec["structures"]]
    prop = vp["volumeProperties"][0]
    assert prop["interpolationType"] == "nearest"
    points = prop["components"][0]["scalarOpacity"]["points"]
    at = {round(p["x"], 2): p["y"] for p in points}
    for s in segments:
        assert at[s["label"] - 0.45] == pytest.approx(s["opacity"])
        assert at[s["label"] + 0.5] == 0.0
    assert any("paraview_preset.json not written" in n for n in report["notes"])


def test_label_volume_property_for_a_seg_spec(files):
    d, _ = files
    spec = load_spec(d / "organs.seg.nrrd")
    vp = slicer_volume_property(spec, opacities=[0.1, 0.3, 0.9])
    rgb = vp["volumeProperties"][0]["components"][0]["rgbTransferFunction"]["points"]
    tumour = [p["color"] for p in rgb if 6.5 < p["x"] < 7.5]
    assert tumour
    assert all(c == [0.1, 0.9, 0.2] for c in tumour)
    assert [s["opacity"] for s in vp["dvr_perception"]["segments"]] == [0.1, 0.3, 0.9]


def _broken(tmp_path, extra=None, segments=SEGMENTS, labels=None, name="bad.seg.nrrd"):
    if labels is None:
        labels = _phantom()[1]
    return write_segmentation(tmp_path / name, labels, segments, extra=extra)


@pytest.mark.parametrize(
    ("extra", "field", "message"),
    [
        ({"Segment1_LabelValue": None}, "Segment1_LabelValue", "is missing"),
        ({"Segment1_LabelValue": "2.5"}, "Segment1_LabelValue", "integer label value"),
        ({"Segment2_LabelValue": "0"}, "Segment2_LabelValue", "1..2147483647"),
        ({"Segment2_LabelValue": "5"}, "Segment2_LabelValue", "duplicates Segment1_LabelValue"),
        ({"Segment0_Color": "1.5 0 0"}, "Segment0_Color", r"in \[0, 1\]"),
        ({"Segment0_Color": "0.5 nan 0"}, "Segment0_Color", r"in \[0, 1\]"),
        ({"Segment0_Color": "1 0"}, "Segment0_Color", "three numbers"),
        ({"Segment0_Color": None}, "Segment0_Color", "is missing"),
        ({"Segment2_Name": "Liver"}, "Segment2_Name", "duplicates Segment1_Name"),
        ({"Segment1_Layer": "1"}, "Segment1_Layer", "single-layer"),
    ],
)
def test_bad_segment_fields_name_the_file_and_field(tmp_path, extra, field, message):
    p = _broken(tmp_path, extra)
    with pytest.raises(DVRInputError, match=message) as info:
        read_segments(p)
    assert "bad.seg.nrrd" in str(info.value)
    assert field in str(info.value)
    code, _, err = _main(["render", "phantom", "--structures", str(p), "--size", "8", "--out",
                          str(tmp_path / "x.png")])  # fmt: skip
    assert code == 2
    assert field in err
    assert "Traceback" not in err
    assert not (tmp_path / "x.png").exists()


def test_too_many_segments_float_data_multilayer_and_no_segments(tmp_path):
    many = [{"name": f"s{i}", "color": (1, 0, 0), "label": i + 1} for i in range(33)]
    with pytest.raises(DVRInputError, match=r"33 segments, more than the 32"):
        read_segments(_broken(tmp_path, segments=many))
    floats = _phantom()[1].astype(np.float32)
    with pytest.raises(DVRInputError, match=r"bad.seg.nrrd: segmentation field 'type'"):
        read_segments(_broken(tmp_path, labels=floats))
    p = _broken(tmp_path, segments=[])
    with pytest.raises(DVRInputError, match=r"bad.seg.nrrd: no 'SegmentN_' header fields"):
        load_spec(p)
    text = _broken(tmp_path).read_bytes()
    head, _, payload = text.partition(b"\n\n")
    head = head.replace(b"dimension: 3", b"dimension: 4").replace(b"sizes: 24", b"sizes: 2 24")
    (tmp_path / "layers.seg.nrrd").write_bytes(head + b"\n\n" + payload)
    with pytest.raises(DVRInputError, match=r"layers.seg.nrrd: a multi-layer segmentation"):
        load_spec(tmp_path / "layers.seg.nrrd")


def test_empty_segmentation_is_one_clear_error(tmp_path):
    # Slicer saves a segmentation without voxels as a single voxel
    p = write_segmentation(tmp_path / "empty.seg.nrrd", np.zeros((1, 1, 1), np.uint8), SEGMENTS)
    with pytest.raises(DVRInputError, match=r"empty.seg.nrrd: the segmentation holds no voxel"):
        segmentation_labels(p, Volume(np.zeros((4, 4, 4), np.uint8)))
    with pytest.raises(DVRInputError, match=r"empty.seg.nrrd: the segmentation holds no voxel"):
        load_spec(p)


def test_hardening_of_the_volume_reader_still_applies(tmp_path):
    p = _broken(tmp_path)
    head, _, payload = p.read_bytes().partition(b"\n\n")
    (tmp_path / "short.seg.nrrd").write_bytes(
        head.replace(b"encoding: gzip", b"encoding: raw") + b"\n\n" + payload[:100]
    )
    with pytest.raises(DVRInputError, match=r"short.seg.nrrd.*truncated"):
        load_spec(tmp_path / "short.seg.nrrd")
    (tmp_path / "elsewhere.seg.nhdr").write_text(
        head.decode("utf-8").replace("encoding: gzip", "encoding: raw")
        + "\ndata file: ../../etc/passwd\n",
        encoding="utf-8",
    )
    with pytest.raises(DVRInputError, match=r"elsewhere.seg.nhdr"):
        load_spec(tmp_path / "elsewhere.seg.nhdr")


def test_vtk_filter_reads_the_segmentation_as_its_spec_file(files):
    from dvr_perception._vtk import vtk_to_numpy
    from dvr_perception.filters import StructuralLayers
    from dvr_perception.volume import to_vtk_image

    d, labels = files
    f = StructuralLayers()
    f.SetSpecFile(str(d / "organs.seg.nrrd"))
    f.SetInputDataObject(to_vtk_image(load_volume(d / "ct.nrrd")))
    f.Update()
    assert f.error_message == ""
    ids = vtk_to_numpy(f.GetOutputDataObject(0).GetPointData().GetAbstractArray("structure_id"))
    expected = np.select([labels == 1, labels == 5, labels == 7], [0, 1, 2], -1)
    np.testing.assert_array_equal(ids.reshape(labels.shape), expected)
