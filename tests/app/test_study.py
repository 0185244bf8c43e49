"""The app's calibration test, ranking task, history and upload checks."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from dvr_perception.app.study import (
    RANKING_FIELDS,
    CalibrationTest,
    RankingTask,
    kendall_agreement,
    png_data_url,
)
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.rays import Camera


def test_calibration_test_rates_every_stimulus_and_saves_a_curve(tmp_path):
    from dvr_perception.calibration import load_calibration

    t = CalibrationTest(seed=3, size=32)
    assert len(t.stimuli) == 8
    assert t.image_url().startswith("data:image/png;base64,")
    with pytest.raises(DVRInputError, match="at least two"):
        t.fit()
    with pytest.raises(DVRInputError, match="0 to 1"):
        t.rate(1.5)
    # a viewer who sees every layer as more see-through than measured
    for m in t.measured:
        t.rate(min(1.0, m + 0.15))
    assert t.done
    with pytest.raises(DVRInputError, match="already rated"):
        t.rate(0.5)
    path, curve = t.save(tmp_path / "me.json")
    with (tmp_path / "me.ratings.csv").open(newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 8
    assert [float(r["rating"]) for r in rows] == pytest.approx(t.ratings, abs=1e-4)
    assert {r["texture"] for r in rows} == {"plain", "textured"}
    saved = load_calibration(path)
    assert saved == curve
    mid = float(saved(0.5))
    assert 0.6 < mid < 0.7  # 0.5 measured is seen as about 0.65


def test_calibration_order_depends_on_the_seed():
    a, b = CalibrationTest(seed=1, size=32), CalibrationTest(seed=2, size=32)
    assert sorted(a.measured) == pytest.approx(sorted(b.measured))
    assert a.measured != b.measured


def test_kendall_agreement():
    assert kendall_agreement(["a", "b", "c"], ["a", "b", "c"]) == (3, 3)
    assert kendall_agreement(["c", "b", "a"], ["a", "b", "c"]) == (0, 3)
    with pytest.raises(DVRInputError, match="different items"):
        kendall_agreement(["a", "b"], ["a", "c"])


def test_ranking_task_records_answers_to_csv(session, tmp_path):
    cam = Camera.from_view(session.volume.bounds, width=48, height=48)
    task = RankingTask.make(session.volume, session.spec, cam, 0, seed=5)
    assert task.structure == session.spec.structures[0].name
    assert sorted(task.shown) == sorted(task.ids)
    assert all(u.startswith("data:image/png") for u in task.urls.values())
    # brighter colour over darker inner layers: the measured see-through differs per image
    values = [task.measured[i] for i in task.ids]
    assert all(v is not None for v in values)
    assert len({round(v, 4) for v in values}) == len(values)
    path = tmp_path / "answers" / "ranking.csv"
    with pytest.raises(DVRInputError, match="all 4 images"):
        task.record(task.ids[:2], path)
    row = task.record(task.measured_order(), path)
    assert row["pairs_agreeing"] == row["pairs_total"] == 6
    task.record(list(reversed(task.measured_order())), path)
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(RANKING_FIELDS)
    assert [r["pairs_agreeing"] for r in rows] == ["6", "0"]
    assert rows[0]["image_ids"].split() == task.shown


def test_ranking_rejects_unknown_structure(session):
    cam = Camera.from_view(session.volume.bounds, width=16, height=16)
    with pytest.raises(DVRInputError, match="no structure"):
        RankingTask.make(session.volume, session.spec, cam, 99)


def test_png_data_url_scales():
    import base64
    import io

    from PIL import Image

    url = png_data_url(np.full((4, 3, 3), 0.5), scale=2)
    img = Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1])))
    assert img.size == (6, 8)
    assert img.getpixel((0, 0)) == (128, 128, 128)


def test_region_structures_lists_only_those_inside(session):
    present = np.zeros((4, 4), dtype=np.uint32)
    present[:2, :2] = 0b001  # structure 0 top left
    present[:, 3] = 0b110  # structures 1 and 2 in the right column
    mask = np.zeros((4, 4), dtype=bool)
    mask[:2, :2] = True
    shares = np.zeros((6, 4, 4), dtype=np.float32)
    shares[0, 0, 0] = 1.0  # structure 0 takes all of pixel (0, 0), 0 of the other three
    rows = session.region_structures(present, mask, shares)
    assert [(r["index"], r["fraction"], r["visible"]) for r in rows] == [(0, 1.0, 0.25)]
    mask[:, 3] = True
    mask[:2, :2] = False
    mask[0, 0] = True  # 1 pixel of structure 0, 4 of structures 1 and 2
    rows = session.region_structures(present, mask)
    assert [(r["index"], r["fraction"]) for r in rows] == [(1, 0.8), (2, 0.8), (0, 0.2)]


def test_history_undo_to_any_step(session):
    original = session.spec
    session.set_structure(0, importance=0.5)
    after_first = session.spec
    session.set_structure(1, colour="#00ff00")
    session.set_structure(2, importance=0.9)
    rows = session.history_rows()
    assert [r["steps"] for r in rows] == [1, 2, 3]
    assert rows[-1]["label"].startswith("importance of")
    assert rows[1]["label"].startswith("colour of")
    assert session.undo(2) == after_first
    assert len(session.history_rows()) == 1
    assert session.undo(5) is None  # more steps than there are
    assert session.undo(1) == original
    assert session.history_rows() == []


def test_upload_checks_type_size_and_content(session, tmp_path):
    from dvr_perception.structures import make_phantom
    from dvr_perception.volume.io import save_volume

    good = tmp_path / "small.nrrd"
    save_volume(make_phantom(size=16)[0], good)
    content = good.read_bytes()
    with pytest.raises(DVRInputError, match="not a volume file"):
        session.store_upload("notes.txt", b"hello")
    with pytest.raises(DVRInputError, match="larger than the limit"):
        session.store_upload("small.nrrd", content, max_bytes=len(content) - 1)
    with pytest.raises(DVRInputError, match="not a readable volume"):
        session.store_upload("fake.nrrd", b"not a volume at all")
    assert not any(session.data_dir.iterdir())  # nothing kept from the bad uploads
    assert not session.upload_dir.exists() or not any(session.upload_dir.iterdir())
    assert session.store_upload("../../small.nrrd", content) == "uploaded/small.nrrd"
    assert (session.upload_dir / "small.nrrd").is_file()
    assert not any(session.data_dir.iterdir())  # uploads never go into the data folder
    assert "uploaded/small.nrrd" in session.volume_choices()
    session.load_volume("uploaded/small.nrrd")
    assert session.volume.data.shape == (16, 16, 16)


def test_calibration_changes_the_transparency_measure(session):
    from dvr_perception.calibration import CalibrationCurve

    cam = Camera.from_view(session.volume.bounds, width=64, height=64)
    plain = session.measure(cam)
    session.use_calibration(CalibrationCurve((0.0, 0.2, 1.0), (0.0, 0.8, 1.0)), "me.json")
    assert session.calibration_name == "me.json"
    calibrated = session.measure(cam)
    assert calibrated.E_t != plain.E_t
    assert calibrated.E_v == plain.E_v
    session.use_calibration(None)
    assert session.measure(cam).E_t == plain.E_t


def test_range_edit_and_bad_ranges(session):
    lo, hi = session.spec.structures[2].range
    session.set_structure(2, value_range=(lo, hi - 10))
    assert session.spec.structures[2].range == (lo, hi - 10)
    assert session.history_rows()[0]["label"] == "range of brain"
    for bad in ((hi, lo), (lo, float("nan")), ("a", 3), (1,)):
        with pytest.raises(DVRInputError, match="range of brain"):
            session.set_structure(2, value_range=bad)
    with pytest.warns(DVRWarning, match="holds no voxel"):
        session.set_structure(2, value_range=(1000, 2000))
