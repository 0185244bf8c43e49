"""The web app's session with 3D Slicer segmentations and label files (issue 21)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception.app.session import PHANTOM, Session
from dvr_perception.errors import DVRInputError
from dvr_perception.rays import Camera
from dvr_perception.structures.slicer import write_segmentation
from dvr_perception.volume.io import save_volume
from dvr_perception.volume.volume import Volume

SEGMENTS = [
    {"name": "shell", "color": (0.2, 0.4, 1.0), "label": 1},
    {"name": "tumour", "color": (1.0, 0.1, 0.1), "label": 7},
]


def _labels():
    lab = np.zeros((16, 16, 16), np.uint8)
    lab[3:13, 3:13, 3:13] = 1
    lab[6:10, 6:10, 6:10] = 7
    return lab


def _spec(labels: str) -> dict:
    core = {"name": "core", "label": 7, "importance": 1.0, "color": [1, 0, 0]}
    return {"version": 1, "labels": labels, "structures": [core]}


@pytest.fixture
def ct(tmp_path):
    """A data folder with a tiny 'CT' (a spread of values: the proposal needs them) and a seg."""
    data = tmp_path / "data"
    data.mkdir()
    rng = np.random.default_rng(21)
    z, y, x = np.mgrid[:16, :16, :16]
    ct = 40 * np.hypot(np.hypot(z - 8, y - 8), x - 8) + rng.integers(0, 40, z.shape)
    save_volume(Volume(ct.astype(np.int16)), data / "ct.nrrd")
    write_segmentation(data / "organs.seg.nrrd", _labels(), SEGMENTS)
    s = Session(data, tmp_path / "exports", state_dir=tmp_path / "state", phantom_size=16)
    s.load_volume("ct.nrrd")
    return s


def test_segmentations_are_offered_as_structures_not_volumes(ct):
    assert ct.volume_choices() == [PHANTOM, "ct.nrrd"]
    assert "organs.seg.nrrd" in ct.spec_choices()


def test_segmentation_loads_as_label_structures_and_renders(ct):
    before = ct.spec
    spec = ct.load_spec_file("organs.seg.nrrd")
    assert [s.name for s in spec.structures] == ["shell", "tumour"]
    assert [s.label for s in spec.structures] == [1, 7]
    assert ct.spec is spec
    assert ct.spec_source == "organs.seg.nrrd"
    assert np.array_equal(ct.volume.labels, _labels())
    assert [r["name"] for r in ct.structure_rows()] == ["shell", "tumour"]
    assert all(r["range"] is None for r in ct.structure_rows())
    cam = Camera.from_view(ct.volume.bounds, azimuth=0, elevation=0, zoom=1.2, width=32, height=32)
    m = ct.measure(cam)
    assert m.shares["tumour"]["visible"] > 0.0  # the engine sees the label structure
    # undo goes back to the proposal and to the volume as loaded (no labels)
    assert ct.undo() is before
    assert ct.volume.labels is None
    assert ct.labels_file is None


def test_spec_json_with_labels_in_the_data_folder(ct):
    save_volume(Volume(_labels()), ct.data_dir / "lab.nhdr")
    spec = _spec("lab.nhdr")
    (ct.data_dir / "withlabels.json").write_text(json.dumps(spec))
    ct.load_spec_file("withlabels.json")
    assert np.array_equal(ct.volume.labels, _labels())


def test_label_file_outside_the_app_folders_is_refused(ct, tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    save_volume(Volume(_labels()), outside / "lab.nhdr")
    spec = _spec("../elsewhere/lab.nhdr")
    (ct.data_dir / "sneaky.json").write_text(json.dumps(spec))
    state = ct.snapshot()
    with pytest.raises(DVRInputError, match="outside the data folder and the settings folder"):
        ct.load_spec_file("sneaky.json")
    assert ct.snapshot()[:4] == state[:4]  # nothing changed
    assert ct.volume.labels is None


def test_bad_segmentation_leaves_the_session_as_it_was(ct):
    write_segmentation(ct.data_dir / "other.seg.nrrd", _labels(), SEGMENTS, spacing=(2, 2, 2))
    state = ct.snapshot()
    with pytest.raises(DVRInputError, match=r"other\.seg\.nrrd"):
        ct.load_spec_file("other.seg.nrrd")
    assert ct.snapshot()[:4] == state[:4]
    assert ct.undo_stack == state[4]


def test_restore_undoes_a_load(ct):
    state = ct.snapshot()
    ct.load_spec_file("organs.seg.nrrd")
    ct.restore(state)
    assert ct.spec is state[2]
    assert ct.volume is state[0]
    assert ct.volume.labels is None
    assert ct.undo_stack == state[4]
