"""The library's loader of a volume, spec and camera (``dvr_perception.inputs``), no CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.inputs import (
    DEFAULT_SIZE,
    OptionParser,
    RenderInputs,
    add_input_args,
    load_inputs,
    load_volume_and_spec,
    read_camera,
)


def _parse(*argv):
    parser = OptionParser(prog="t")
    add_input_args(parser)
    return parser.parse_args(list(argv))


def test_phantom_with_size_and_view():
    got = load_inputs(_parse("phantom", "--size", "24x16", "--view", "30,10,2"))
    assert isinstance(got, RenderInputs)
    assert (got.camera.width, got.camera.height) == (24, 16)
    assert got.volume.dims == (128, 128, 128)
    assert got.spec_source == "phantom (built-in spec)"
    assert got.spec_line == ""
    assert got.spec.names[0] == "skin"


def test_the_default_size_and_the_specs_view():
    got = load_inputs(_parse("phantom", "--no-shade"))
    assert (got.camera.width, got.camera.height) == (DEFAULT_SIZE, DEFAULT_SIZE)
    assert got.spec.rendering.shade is False


def test_a_preset_by_name_says_so_in_one_line(tmp_path):
    from dvr_perception.volume import Volume, save_volume

    save_volume(Volume(np.zeros((6, 7, 8), np.uint8)), tmp_path / "v.nhdr")
    argv = (str(tmp_path / "v.nhdr"), "--preset", "tooth", "--size", "8")
    with pytest.warns(DVRWarning, match="holds no voxel"):  # zeros: the preset's ranges are empty
        got = load_inputs(_parse(*argv))
    assert got.spec_line == "structures: preset 'tooth' (given with --preset)"
    assert got.spec_source.endswith("tooth.json")
    assert got.volume.dims == (8, 7, 6)


def test_camera_file_round_trip(tmp_path):
    first = load_inputs(_parse("phantom", "--size", "12"))
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(first.camera.to_dict()), encoding="utf-8")
    cam = read_camera(path, (20, 10))
    assert (cam.width, cam.height) == (20, 10)
    np.testing.assert_allclose(cam.position, first.camera.position)
    again = load_inputs(_parse("phantom", "--camera", str(path)))
    assert (again.camera.width, again.camera.height) == (12, 12)


def test_volume_and_spec_alone_and_unpaired(tmp_path):
    vol, spec, source, line = load_volume_and_spec("phantom")
    assert len(spec.structures) == 6
    assert source == "phantom (built-in spec)"
    assert line == ""
    from dvr_perception.volume import Volume, save_volume

    save_volume(Volume(np.arange(64, dtype=np.uint8).reshape(4, 4, 4)), tmp_path / "a.nhdr")
    vol, spec, source, line = load_volume_and_spec(str(tmp_path / "a.nhdr"), paired=False)
    assert vol.dims == (4, 4, 4)
    assert (spec, source, line) == (None, "", "")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["phantom", "--size", "0"], "--size: width and height must be in 1..16384"),
        (["phantom", "--view", "a,b"], "--view"),
        (
            ["phantom", "--camera", "/no/such/cam.json"],
            "--camera /no/such/cam.json: file not found",
        ),
        (["phantom", "--memory-limit", "12"], "--memory-limit: expected a memory size"),
        (["phantom", "--size", "8", "--preset", "x", "--classes", "2"], "not allowed with"),
    ],
)
def test_bad_options_are_one_input_error(argv, message, monkeypatch):
    from dvr_perception import _memory

    monkeypatch.setattr(_memory, "_LIMIT", [None])
    with pytest.raises(DVRInputError, match=message.replace(".", r"\.").replace("(", r"\(")):
        load_inputs(_parse(*argv))
