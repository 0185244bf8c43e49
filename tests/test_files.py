"""Tests for dvr_perception._files (atomic writers)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception._files import (
    atomic_path,
    json_ready,
    read_png,
    write_json,
    write_npz,
    write_png,
)
from dvr_perception.errors import DVRInputError


def _write_then_fail(target, seen):
    with atomic_path(target) as tmp:
        tmp.write_text("partial")
        seen.append(tmp)
        raise RuntimeError("boom")


def test_atomic_path_error_leaves_nothing(tmp_path):
    seen = []
    with pytest.raises(RuntimeError, match="boom"):
        _write_then_fail(tmp_path / "out.txt", seen)
    assert len(seen) == 1  # the temporary file was created, then removed
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_error_keeps_old_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        _write_then_fail(target, [])
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_path_success_replaces(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path
        assert tmp.suffix == ".txt"
        assert not tmp.exists()
        tmp.write_text("new")
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_path_nothing_written_is_error(tmp_path):
    with pytest.raises(OSError, match="nothing was written"), atomic_path(tmp_path / "x.txt"):
        pass
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_missing_directory(tmp_path):
    with (
        pytest.raises(DVRInputError, match="does not exist"),
        atomic_path(tmp_path / "nope" / "x.txt"),
    ):
        pass


def test_png_round_trip_rgb_float(tmp_path):
    img = np.zeros((3, 5, 3))
    img[0, 0] = (1.0, 0.0, 0.0)  # top-left red
    img[2, 4] = (0.0, 0.0, 1.0)  # bottom-right blue
    img[1, 2] = (0.5, 0.5, 0.5)
    out = write_png(tmp_path / "a.png", img)
    back = read_png(out)
    assert back.shape == (3, 5, 3)
    assert back.dtype == np.uint8
    assert tuple(back[0, 0]) == (255, 0, 0)
    assert tuple(back[2, 4]) == (0, 0, 255)
    assert tuple(back[1, 2]) == (128, 128, 128)
    assert back.sum() == 255 * 2 + 128 * 3


def test_png_round_trip_rgba_uint8_exact(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, size=(7, 4, 4), dtype=np.uint8)
    write_png(tmp_path / "b.png", img)
    np.testing.assert_array_equal(read_png(tmp_path / "b.png"), img)


def test_png_with_matplotlib_reader(tmp_path):
    import matplotlib.image as mpimg

    img = np.zeros((2, 2, 3), np.uint8)
    img[0, 1] = 255
    write_png(tmp_path / "c.png", img)
    back = mpimg.imread(tmp_path / "c.png")
    assert back.shape == (2, 2, 3)
    assert back[0, 1].tolist() == [1.0, 1.0, 1.0]
    assert back[1, 0].tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((4, 4)), r"shape \(height, width, 3 or 4\)"),
        (np.zeros((4, 4, 2)), "3 or 4"),
        (np.full((2, 2, 3), 1.5), r"\[0, 1\]"),
        (np.full((2, 2, 3), np.nan), "NaN"),
        (np.zeros((2, 2, 3), np.int32), "dtype int32"),
    ],
)
def test_png_bad_images(tmp_path, image, match):
    with pytest.raises(DVRInputError, match=match):
        write_png(tmp_path / "bad.png", image)
    assert list(tmp_path.iterdir()) == []


def test_json_numpy_conversion(tmp_path):
    obj = {
        "f": np.float32(0.25),
        "i": np.int64(3),
        "arr": np.arange(3, dtype=np.uint8),
        "t": (1, 2),
        "nan": float("nan"),
        "b": np.bool_(True),
    }
    write_json(tmp_path / "x.json", obj)
    text = (tmp_path / "x.json").read_text()
    assert text.startswith('{\n  "f": 0.25')
    assert json.loads(text) == {
        "f": 0.25,
        "i": 3,
        "arr": [0, 1, 2],
        "t": [1, 2],
        "nan": None,
        "b": True,
    }


def test_json_unconvertible_writes_nothing(tmp_path):
    with pytest.raises(DVRInputError, match="object"):
        write_json(tmp_path / "x.json", {"a": object()})
    assert list(tmp_path.iterdir()) == []


def test_json_ready_nested():
    assert json_ready([np.array([[1.5]]), {"k": np.inf}]) == [[[1.5]], {"k": None}]


def test_npz_round_trip_exact_name(tmp_path):
    out = write_npz(tmp_path / "buf.bin", a=np.eye(2), names=np.array(["x", "yy"]), s="cam")
    assert out == tmp_path / "buf.bin"
    assert [p.name for p in tmp_path.iterdir()] == ["buf.bin"]
    with np.load(out) as data:
        np.testing.assert_array_equal(data["a"], np.eye(2))
        assert data["names"].tolist() == ["x", "yy"]
        assert str(data["s"]) == "cam"


def test_npz_refuses_object_arrays(tmp_path):
    with pytest.raises(DVRInputError, match="'bad'"):
        write_npz(tmp_path / "b.npz", bad=np.array([{}, 1], dtype=object))
    assert list(tmp_path.iterdir()) == []


def test_files_are_written_when_sigint_has_a_c_handler(tmp_path, monkeypatch):
    """pvpython installs its own C SIGINT handler: Python sees ``None`` and cannot restore it."""
    from dvr_perception import _files

    def refuse(*_):
        raise AssertionError("signal.signal must not be called over a C handler")

    monkeypatch.setattr(_files.signal, "getsignal", lambda _sig: None)
    monkeypatch.setattr(_files.signal, "signal", refuse)
    with _files.atomic_path(tmp_path / "a.txt") as tmp:
        tmp.write_text("x")
    with _files.output_folder(tmp_path / "out") as staged:
        (staged.path / "b.txt").write_text("y")
    assert (tmp_path / "a.txt").read_text() == "x"
    assert (tmp_path / "out" / "b.txt").read_text() == "y"
