"""The CLI reads a spec's label volume ("labels" file) and renders its label structures."""

from __future__ import annotations

import json

import numpy as np

from dvr_perception._files import read_png
from dvr_perception.cli import main
from dvr_perception.volume.io import save_volume
from dvr_perception.volume.volume import Volume


def _files(tmp_path, label_shape=(16, 18, 20)):
    x = np.mgrid[:16, :18, :20][2]
    data = (60 + 2 * x).astype(np.uint8)
    save_volume(Volume(data), tmp_path / "vol.nhdr")
    labels = np.zeros(label_shape, np.uint8)
    labels[5:11, 6:12, 7:13] = 4
    save_volume(Volume(labels), tmp_path / "lab.nhdr")
    spec = {
        "version": 1,
        "labels": "lab.nhdr",
        "rendering": {"shade": False},
        "structures": [
            {"name": "ramp", "range": [200, 250], "importance": 0.5, "color": [1, 1, 1]},
            {"name": "cube", "label": 4, "importance": 1.0, "color": [1, 0, 0]},
        ],
    }
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    return tmp_path / "vol.nhdr", tmp_path / "spec.json"


def test_render_shows_the_labelled_cube(tmp_path, capsys):
    vol, spec = _files(tmp_path)
    out = tmp_path / "img.png"
    code = main(["render", str(vol), "--structures", str(spec), "--size", "40", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    img = read_png(out)
    red = (img[..., 0] > 0.5) & (img[..., 1] < 0.2)
    assert 50 < red.sum() < 0.5 * red.size  # the cube, red, and not the whole frame


def test_label_file_of_other_dims_is_one_clear_error(tmp_path, capsys):
    vol, spec = _files(tmp_path, label_shape=(16, 18, 21))
    code = main(["render", str(vol), "--structures", str(spec), "--out", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert code == 2
    assert "labels file" in err
    assert "do not match" in err
    assert "Traceback" not in err
    assert not (tmp_path / "x.png").exists()
