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
    (session.data_dir / "my head.nrrd").write_text("x")
    (session.data_dir / ".hidden.nrrd").write_text("x")
    (session.data_dir / "notes.txt").write_text("x")
    assert session.volume_choices() == [PHANTOM, "a.nhdr", "my head.nrrd"]


@pytest.mark.parametrize("name", ["../x.json", "/etc/passwd", "sub/../../x.json"])
def test_paths_outside_the_data_folder_are_refused(session, name):
    with pytest.raises(DVRInputError, match="outside the data folder"):
        session.data_path(name, must_exist=False)


@pytest.mark.parametrize("name", ["../x.json", "/etc/passwd", "saved/../../x.json", "x.json"])
def test_only_offered_settings_files_load(session, name):
    (session.data_dir.parent / "x.json").write_text("{}", encoding="utf-8")
    with pytest.raises(DVRInputError, match="not one of the settings files offered"):
        session.load_spec_file(name)


@pytest.mark.parametrize("name", ["../x.json", "/tmp/x.json", "sub/x.json", ".x.json", "x.txt"])
def test_settings_are_saved_under_plain_names_only(session, name):
    with pytest.raises(DVRInputError, match=r"plain file name|ending in"):
        session.save_spec_file(name)
    assert not (session.data_dir.parent / "x.json").exists()
    assert not session.settings_dir.exists() or not any(session.settings_dir.iterdir())


def test_read_only_data_folder_and_writes_into_the_state_folder(tmp_path):
    import os

    from dvr_perception.volume import make_phantom
    from dvr_perception.volume.io import save_volume

    data = tmp_path / "data"
    data.mkdir()
    save_volume(make_phantom(size=16)[0], data / "small.nrrd")
    content = (data / "small.nrrd").read_bytes()
    data.chmod(0o555)
    try:
        s = Session(data, state_dir=tmp_path / "state", phantom_size=16)
        s.load_volume("small.nrrd")
        assert s.save_spec_file("mine.json") == "saved/mine.json"
        assert s.store_upload("copy.nrrd", content) == "uploaded/copy.nrrd"
        files = s.export()
        assert sorted(os.listdir(data)) == ["small.nrrd"]
        assert all(p.is_relative_to(tmp_path / "state") for p in files)
        assert s.export_dir == (tmp_path / "state" / "exports").resolve()
        assert (tmp_path / "state").stat().st_mode & 0o077 == 0  # private to the user
    finally:
        data.chmod(0o755)


def test_default_state_folder_follows_xdg(monkeypatch, tmp_path):
    from dvr_perception.app.session import default_state_dir

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert default_state_dir() == tmp_path / "xdg" / "dvr-perception"


def test_no_data_folder_refuses_files(tmp_path):
    s = Session(None, tmp_path, state_dir=tmp_path / "state")
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
    assert session.save_spec_file("edited.json") == "saved/edited.json"
    assert (session.settings_dir / "edited.json").is_file()
    assert not any(session.data_dir.iterdir())  # the data folder is only read
    assert "saved/edited.json" in session.spec_choices()
    assert session.undo() == original
    session.load_spec_file("saved/edited.json")
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
