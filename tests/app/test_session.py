"""The web app's framework-free part: files restricted to the data folder, edits, undo, export."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception.app.session import PHANTOM, Session, hex_to_rgb, rgb_to_hex
from dvr_perception.errors import DVRInputError
from dvr_perception.rays import Camera


def test_volume_choices_list_phantom_and_volume_files(session):
    (session.data_dir / "a.nhdr").write_text("x")
    (session.data_dir / "notes.txt").write_text("x")
    assert session.volume_choices() == [PHANTOM, "a.nhdr"]


@pytest.mark.parametrize("name", ["../x.json", "/etc/passwd", "sub/../../x.json"])
def test_paths_outside_the_data_folder_are_refused(session, name):
    with pytest.raises(DVRInputError, match="outside the data folder"):
        session.data_path(name, must_exist=False)


def test_no_data_folder_refuses_files(tmp_path):
    s = Session(None, tmp_path)
    with pytest.raises(DVRInputError, match="no data folder"):
        s.data_path("spec.json")


def test_malformed_spec_file_is_an_input_error(session):
    (session.data_dir / "bad.json").write_text("{", encoding="utf-8")
    with pytest.raises(DVRInputError):
        session.load_spec_file("bad.json")
    assert session.undo_stack == []


def test_edit_save_load_and_undo(session):
    original = session.spec
    session.set_structure(0, importance=0.5, color="#ff0000")
    assert session.spec.structures[0].importance == 0.5
    assert session.spec.structures[0].color == (1.0, 0.0, 0.0)
    session.save_spec_file("edited.json")
    assert session.undo() == original
    session.load_spec_file("edited.json")
    assert session.spec.structures[0].importance == 0.5
    with pytest.raises(DVRInputError, match="0 to 1"):
        session.set_structure(0, importance=2)
    with pytest.raises(DVRInputError, match="rrggbb"):
        session.set_structure(0, color="red")


def test_export_writes_spec_and_presets(session):
    files = session.export()
    assert [p.name for p in files] == [
        "phantom_spec.json",
        "phantom_paraview.json",
        "phantom.vp.json",
    ]
    for p in files:
        json.loads(p.read_text())


def test_measure_gives_errors_and_maps_without_background(session):
    cam = Camera.from_view(session.volume.bounds, width=600, height=300)
    m = session.measure(cam)
    assert m.images["visibility"].shape == (128, 256)
    assert all(v >= 0 for v in (m.E_v, m.E_s, m.E_t))
    assert np.isnan(m.images["shape"][0, 0])  # corner: empty ray, no map


def test_colour_round_trip():
    assert rgb_to_hex(hex_to_rgb("#12ab3f")) == "#12ab3f"
