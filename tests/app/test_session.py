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

    from dvr_perception.structures import make_phantom
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
    session.set_structure(0, importance=0.5, colour="#ff0000")
    assert session.spec.structures[0].importance == 0.5
    assert session.spec.structures[0].colour == (1.0, 0.0, 0.0)
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
        session.set_structure(0, colour="red")
    with pytest.warns(DeprecationWarning, match=r"set_structure\(color=\.\.\.\) is deprecated"):
        session.set_structure(1, color="#00ff00")  # the old keyword, for one release
    assert session.spec.structures[1].colour == (0.0, 1.0, 0.0)


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


def test_orientation_of_a_file_that_records_none(tmp_path):
    """The Data screen's Orientation field: LPI re-orders the volume and its labels along z,
    marks it oriented and ends the patient-view note; a bad code is one error naming the field
    and changes nothing; "" goes back to the axes as stored; a file with one is refused."""
    from dvr_perception.volume.io import save_volume
    from dvr_perception.volume.volume import Volume

    data = tmp_path / "data"
    data.mkdir()
    z, y, x = np.mgrid[:12, :10, :8]
    values = (20 * z + x + 300 * (np.hypot(y - 5, x - 4) < 3)).astype(np.int16)
    labels = (values > 200).astype(np.uint8) * 3
    save_volume(Volume(values, oriented=False), data / "plain.nrrd")  # no 'space' field
    save_volume(Volume(labels, oriented=False), data / "lab.nhdr")
    spec = {"version": 1, "labels": "lab.nhdr", "structures": [
        {"name": "core", "label": 3, "importance": 1.0, "color": [1, 0, 0]}]}  # fmt: skip
    (data / "core.json").write_text(json.dumps(spec))
    s = Session(data, tmp_path / "exports", state_dir=tmp_path / "state", phantom_size=40)
    s.load_volume("plain.nrrd")
    s.load_spec_file("core.json")
    assert s.volume.oriented is False
    assert "Data screen's Orientation field" in s.patient_view_note()
    assert s.undo_stack  # the spec load can be undone
    s.set_orientation("lpi")
    assert s.volume.oriented is True
    assert s.orientation == "LPI"
    np.testing.assert_array_equal(s.volume.data, values[::-1])  # slice 0 was the top
    np.testing.assert_array_equal(s.volume.labels, labels[::-1])  # labels with the data
    assert s.patient_view_note() is None
    assert not s.undo_stack  # a new volume, as after a load
    shown = s.volume
    with pytest.raises(DVRInputError, match=r"^Orientation: expected three letters.*'LPQ'"):
        s.set_orientation("LPQ")
    assert s.volume is shown
    assert s.orientation == "LPI"
    assert s.with_labels(s.spec)[0] is shown  # undo/redo keep the re-ordered labels
    s.set_orientation("")
    assert s.volume.oriented is False
    np.testing.assert_array_equal(s.volume.data, values)
    np.testing.assert_array_equal(s.volume.labels, labels)
    s.load_volume(PHANTOM)  # records its orientation: no code accepted
    with pytest.raises(DVRInputError, match="phantom records its patient orientation"):
        s.set_orientation("LPI")
    s.load_volume("plain.nrrd", orientation="RAI")  # as `dvr-perception app --orientation`
    assert s.volume.oriented is True
    np.testing.assert_array_equal(s.volume.data, values[::-1, ::-1, ::-1])
