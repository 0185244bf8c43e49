"""Spec JSON: validation messages, round trip, atomic save, volume checks."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures import (
    Lighting,
    RenderSettings,
    check_spec_for_volume,
    load_spec,
    save_spec,
    spec_from_dict,
    spec_to_dict,
)
from dvr_perception.volume import Volume


def _minimal() -> dict:
    return {
        "version": 1,
        "structures": [
            {"name": "skin", "range": [10, 20], "importance": 0.3, "color": [1, 0.8, 0.7]},
            {"name": "bone", "range": [20, 40], "importance": 0.9, "color": [1, 1, 1]},
        ],
    }


def _full() -> dict:
    return {
        "version": 1,
        "background": [0.1, 0.2, 0.3],
        "structures": [
            {
                "name": "skin",
                "range": [10.0, 20.0],
                "importance": 0.3,
                "colour": [1.0, 0.8, 0.7],
                "edge": 0.25,
                "lighting": {
                    "ambient": 0.1,
                    "diffuse": 0.7,
                    "specular": 0.5,
                    "specular_power": 32.0,
                },
                "opacity": 0.2,
                "expected_opacity": 0.4,
            },
            {
                "name": "organ",
                "label": 3,
                "importance": 1.0,
                "colour": [1.0, 0.0, 0.0],
                "edge": 0.1,
                "lighting": {
                    "ambient": 0.2,
                    "diffuse": 0.8,
                    "specular": 0.2,
                    "specular_power": 16.0,
                },
            },
        ],
        "rendering": {
            "shade": False,
            "sample_distance": 0.5,
            "opacity_unit_distance": 2.0,
            "light_direction": [0.0, 1.0, 1.0],
            "light_intensity": 0.8,
        },
        "view": [30.0, -20.0, 1.5],
        "labels": "labels.nhdr",
    }


def test_minimal_defaults():
    spec = spec_from_dict(_minimal())
    assert spec.names == ("skin", "bone")
    assert spec.structures[0].range == (10.0, 20.0)
    assert spec.structures[0].lighting == Lighting()
    assert spec.structures[0].edge == 0.1
    assert spec.structures[1].opacity is None
    assert spec.rendering == RenderSettings()
    assert spec.background == (0.0, 0.0, 0.0)
    assert spec.view is None
    assert spec.labels_file is None


def test_full_round_trip_is_exact():
    d = _full()
    spec = spec_from_dict(d)
    assert spec.structures[1].label == 3
    assert spec.structures[0].lighting.specular_power == 32.0
    assert spec.rendering.shade is False
    assert spec_to_dict(spec) == d
    assert spec_from_dict(spec_to_dict(spec)) == spec


def test_minimal_round_trip_normalises():
    d = spec_to_dict(spec_from_dict(_minimal()))
    assert d["structures"][0]["lighting"] == {
        "ambient": 0.2,
        "diffuse": 0.8,
        "specular": 0.2,
        "specular_power": 16.0,
    }
    assert "opacity" not in d["structures"][0]
    assert "view" not in d
    assert spec_to_dict(spec_from_dict(d)) == d


def test_view_with_two_numbers_gets_zoom_one():
    d = _minimal()
    d["view"] = [10, 20]
    assert spec_from_dict(d).view == (10.0, 20.0, 1.0)


def _set(path: str, value):
    """Return a mutator setting a dotted/indexed field of the minimal spec (None deletes)."""

    def mutate(d):
        keys = path.replace("[", ".").replace("]", "").split(".")
        obj = d
        for k in keys[:-1]:
            obj = obj[int(k)] if k.isdigit() else obj.setdefault(k, {})
        last = int(keys[-1]) if keys[-1].isdigit() else keys[-1]
        if value is _DELETE:
            del obj[last]
        else:
            obj[last] = value
        return d

    return mutate


_DELETE = object()

BAD = [
    (_set("version", _DELETE), "version is missing"),
    (_set("version", 2), "version must be 1, got 2"),
    (_set("version", True), "version must be 1"),
    (_set("structures", []), "structures must be a non-empty list"),
    (_set("structures", {"a": 1}), "structures must be a non-empty list"),
    (_set("structures[1].name", "skin"), "structures[1].name duplicates structures[0].name"),
    (_set("structures[0].name", "  "), "structures[0].name must be a non-empty string"),
    (_set("structures[0].label", 2), "structures[0] must have exactly one of 'range'"),
    (_set("structures[0].range", _DELETE), "structures[0] must have exactly one of 'range'"),
    (_set("structures[0].range", [20, 10]), "structures[0].range must be [lo, hi] with lo < hi"),
    (_set("structures[0].range", [1, 2, 3]), "structures[0].range must be a list of 2"),
    (_set("structures[0].range", ["a", 2]), "structures[0].range[0] must be a number"),
    (_set("structures[1].importance", 1.5), "structures[1].importance must be in (0, 1], got 1.5"),
    (_set("structures[1].importance", 0), "structures[1].importance must be in (0, 1], got 0"),
    (_set("structures[1].importance", _DELETE), "structures[1].importance is missing"),
    (_set("structures[0].color", [1, 2, 0]), "structures[0].color[1] must be in [0, 1], got 2"),
    (_set("structures[0].color", [1, 1]), "structures[0].color must be a list of 3 numbers"),
    (_set("structures[0].lighting.ambient", -0.1), "structures[0].lighting.ambient must be in"),
    (_set("structures[0].lighting.specular", 1.2), "structures[0].lighting.specular must be"),
    (
        _set("structures[0].lighting.specular_power", 0),
        "structures[0].lighting.specular_power must be in (0, 128]",
    ),
    (_set("structures[0].lighting.specular_power", 200), "specular_power must be in (0, 128]"),
    (_set("structures[0].expected_opacity", 1.1), "structures[0].expected_opacity must be in"),
    (_set("structures[0].opacity", -0.5), "structures[0].opacity must be in [0, 1]"),
    (_set("structures[0].edge", 0.6), "structures[0].edge must be in [0, 0.5], got 0.6"),
    (_set("structures[1].range", [15, 40]), "overlaps structures[0].range [10, 20] of 'skin'"),
    (_set("structures[0].range", [0, 100]), "'bone' overlaps structures[0].range [0, 100]"),
    (_set("structures[0].importance", math.nan), "structures[0].importance must be a finite"),
    (_set("rendering.sample_distance", math.inf), "rendering.sample_distance must be a finite"),
    (_set("future.thing", math.nan), "future.thing must be a finite number"),
    (_set("background", [0, 0, 2]), "background[2] must be in [0, 1]"),
    (_set("rendering.shade", "yes"), "rendering.shade must be true or false"),
    (_set("rendering.sample_distance", 0), "rendering.sample_distance must be in (0, inf)"),
    (_set("rendering.light_direction", [0, 0, 0]), "light_direction must be a non-zero vector"),
    (_set("view", [0, 0, 0]), "view[2] (zoom) must be positive"),
    (_set("view", [1]), "view must be a list of 2 or 3"),
    (_set("labels", 5), "labels must be a non-empty path string"),
]


@pytest.mark.parametrize(("mutate", "message"), BAD)
def test_bad_field_raises_one_clear_error(mutate, message):
    d = mutate(copy.deepcopy(_minimal()))
    with pytest.raises(DVRInputError) as info:
        spec_from_dict(d, source="spec.json")
    text = str(info.value)
    assert text.startswith("spec.json: ")
    assert message in text
    assert "\n" not in text


def test_label_errors():
    d = _minimal()
    d["structures"][0] = {"name": "a", "label": 1, "importance": 0.5, "color": [1, 1, 1]}
    with pytest.raises(DVRInputError, match=r"structures\[0\]\.label needs a 'labels' file"):
        spec_from_dict(d)
    d["labels"] = "l.nhdr"
    d["structures"][1] = {"name": "b", "label": 1, "importance": 0.5, "color": [1, 1, 1]}
    with pytest.raises(DVRInputError, match=r"structures\[1\]\.label duplicates structures\[0\]"):
        spec_from_dict(d)
    d["structures"][1]["label"] = 1.0
    with pytest.raises(DVRInputError, match="must be an integer label id"):
        spec_from_dict(d)


def test_touching_ranges_are_allowed():
    spec = spec_from_dict(_minimal())
    assert spec.structures[0].range[1] == spec.structures[1].range[0]


def test_not_an_object():
    with pytest.raises(DVRInputError, match="top level must be a JSON object"):
        spec_from_dict([1, 2], source="x.json")


def test_unknown_keys_warn_once_naming_them():
    d = _minimal()
    d["comment"] = "hi"
    d["structures"][1]["texture"] = 1
    with pytest.warns(DVRWarning, match=r"comment, structures\[1\]\.texture") as rec:
        spec = spec_from_dict(d)
    assert len(rec) == 1
    assert spec.names == ("skin", "bone")


def test_save_load_round_trip(tmp_path):
    spec = spec_from_dict(_minimal())
    path = tmp_path / "s.json"
    save_spec(spec, path)
    assert load_spec(path) == spec
    assert json.loads(path.read_text())["version"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["s.json"]  # no temp file left behind


def test_save_overwrites_atomically(tmp_path):
    path = tmp_path / "s.json"
    path.write_text("old")
    save_spec(spec_from_dict(_minimal()), path)
    assert load_spec(path).names == ("skin", "bone")


def test_labels_path_is_relative_to_the_spec_file(tmp_path):
    sub = tmp_path / "a"
    sub.mkdir()
    (sub / "labels.nhdr").write_text("x")
    d = _full()
    (sub / "spec.json").write_text(json.dumps(d))
    spec = load_spec(sub / "spec.json")
    assert spec.labels_file == str((sub / "labels.nhdr").resolve())
    save_spec(spec, tmp_path / "copy.json")
    assert json.loads((tmp_path / "copy.json").read_text())["labels"] == "a/labels.nhdr"
    assert load_spec(tmp_path / "copy.json").labels_file == spec.labels_file


def test_missing_labels_file(tmp_path):
    (tmp_path / "spec.json").write_text(json.dumps(_full()))
    with pytest.raises(DVRInputError, match=r"spec\.json: labels file 'labels\.nhdr' not found"):
        load_spec(tmp_path / "spec.json")


def test_json_syntax_error_names_line(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text('{\n  "version": 1,\n  "structures": [,]\n}\n')
    with pytest.raises(DVRInputError, match=r"bad\.json: not valid JSON at line 3"):
        load_spec(path)


def test_nan_in_file(tmp_path):
    path = tmp_path / "nan.json"
    text = json.dumps(_minimal()).replace("0.3", "NaN")
    path.write_text(text)
    with pytest.raises(DVRInputError, match=r"structures\[0\]\.importance must be a finite"):
        load_spec(path)


def test_missing_file(tmp_path):
    with pytest.raises(DVRInputError, match="spec file not found"):
        load_spec(tmp_path / "nope.json")


def test_check_spec_for_volume_warns_for_empty_range():
    data = np.zeros((2, 3, 4), np.uint8)
    data[0, 0, :2] = 15
    vol = Volume(data, name="v")
    spec = spec_from_dict(_minimal())
    with pytest.warns(DVRWarning, match=r"'bone': range \[20, 40\] holds no voxel"):
        msgs = check_spec_for_volume(spec, vol)
    assert len(msgs) == 1
    assert "bone" in msgs[0]


def test_check_spec_for_volume_float_and_edges():
    data = np.full((2, 2, 2), 40.0)
    data[0, 0, 0] = 10.0  # exactly at the lower end of 'skin'
    msgs = check_spec_for_volume(spec_from_dict(_minimal()), Volume(data))
    assert msgs == []


def test_check_spec_for_volume_labels():
    d = _full()
    spec = spec_from_dict(d)
    data = np.full((2, 2, 2), 12, np.uint8)
    with pytest.raises(DVRInputError, match="'organ': label 3 needs a label volume"):
        check_spec_for_volume(spec, Volume(data))
    labels = np.zeros((2, 2, 2), np.uint8)
    with pytest.warns(DVRWarning, match="label 3 does not occur"):
        check_spec_for_volume(spec, Volume(data, labels=labels))
    labels[1, 1, 1] = 3
    assert check_spec_for_volume(spec, Volume(data, labels=labels)) == []
