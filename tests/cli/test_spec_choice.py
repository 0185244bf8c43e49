"""Which spec a command uses and why (one line), ``--preset``/``--classes``, the default view."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception.cli import main
from dvr_perception.rays.camera import Camera, patient_view
from dvr_perception.structures.presets import presets_dir
from dvr_perception.volume import Volume, load_volume, save_volume


def _run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _scan(oriented=False):
    rng = np.random.default_rng(2)
    data = rng.integers(0, 30, (12, 14, 16)).astype(np.uint8)
    data[3:9, 4:10, 5:11] = 120 + rng.integers(0, 20, (6, 6, 6))
    data[5:7, 6:8, 7:9] = 220
    return Volume(data, spacing=(1.0, 1.0, 1.5), oriented=oriented)


def _render(capsys, tmp_path, volume_path, *extra):
    argv = ["render", str(volume_path), "--size", "16", "--out", str(tmp_path / "o.png")]
    code, out, err = _run(capsys, [*argv, *extra, "--json"])
    assert code == 0, err
    return json.loads(out), err


def test_a_file_named_like_a_shared_volume_gets_a_proposal_and_says_so(capsys, tmp_path):
    save_volume(_scan(), tmp_path / "tooth.nhdr")  # the name of a preset, other content
    report, err = _render(capsys, tmp_path, tmp_path / "tooth.nhdr")
    assert report["spec"] == "proposed"
    assert "structures proposed from the data (no preset matches this file)\n" in err
    assert not any(n in ("dentin", "enamel") for n in report["structures"])


def test_preset_by_name_and_count_by_classes(capsys, tmp_path):
    save_volume(_scan(), tmp_path / "scan.nhdr")
    report, err = _render(capsys, tmp_path, tmp_path / "scan.nhdr", "--preset", "tooth")
    assert report["spec"] == str(presets_dir() / "tooth.json")
    assert "structures: preset 'tooth' (given with --preset)\n" in err
    report, err = _render(capsys, tmp_path, tmp_path / "scan.nhdr", "--classes", "2")
    assert len(report["structures"]) == 2
    assert "structures proposed from the data (2 requested with --classes)\n" in err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--preset", "nosuch"], "--preset 'nosuch': no such preset (known: HeadMRVolume, "),
        (["--classes", "9"], "--classes: expected 'auto' or an integer from 1 to 8, got 9"),
        (["--classes", "2", "--preset", "tooth"], "not allowed with argument"),
    ],
)
def test_bad_choices_are_one_line_errors(capsys, tmp_path, extra, message):
    save_volume(_scan(), tmp_path / "scan.nhdr")
    code, _, err = _run(
        capsys, ["render", str(tmp_path / "scan.nhdr"), "--out", str(tmp_path / "o.png"), *extra]
    )
    assert code == 2
    assert message in err
    assert err.count("\n") == 1
    assert not (tmp_path / "o.png").exists()


@pytest.mark.shared_data
def test_a_shared_volume_saved_elsewhere_keeps_its_preset(capsys, tmp_path, shared_data):
    save_volume(load_volume(shared_data / "neghip.nhdr"), tmp_path / "mine.vti")
    report, err = _render(capsys, tmp_path, tmp_path / "mine.vti")
    assert report["spec"] == str(presets_dir() / "neghip.json")
    assert "structures: preset 'neghip' (data checksum matches)\n" in err
    report, err = _render(capsys, tmp_path, tmp_path / "mine.vti", "--classes", "auto")
    assert report["spec"] == "proposed"
    assert "structures proposed from the data (asked with --classes auto)\n" in err
    assert all(n.startswith("class ") for n in report["structures"])


def test_default_view_of_an_oriented_scan_is_anterior_head_up(capsys, tmp_path):
    save_volume(_scan(oriented=True), tmp_path / "ct.nrrd")
    vol = load_volume(tmp_path / "ct.nrrd")
    assert vol.oriented
    report, err = _render(capsys, tmp_path, tmp_path / "ct.nrrd")
    cam = Camera.from_dict(report["camera"])
    want = patient_view(vol, "anterior", width=16, height=16)
    np.testing.assert_allclose(cam.position, want.position, atol=1e-9)
    np.testing.assert_allclose(cam.view_up, (0.0, 0.0, 1.0), atol=1e-12)  # head (+S) up
    assert cam.position[1] < vol.center[1]  # in front of the patient (anterior is -y in LPS)
    assert "orientation" not in err  # no warning: the file records its orientation
    # --view A,E,Z keeps its meaning: relative to the down -z view
    report, _ = _render(capsys, tmp_path, tmp_path / "ct.nrrd", "--view=0,0,1")
    cam = Camera.from_dict(report["camera"])
    np.testing.assert_allclose(cam.view_up, (0.0, 1.0, 0.0), atol=1e-12)


def test_a_file_without_orientation_keeps_the_down_z_default_and_the_warning(capsys, tmp_path):
    save_volume(_scan(oriented=False), tmp_path / "raw.nhdr")
    vol = load_volume(tmp_path / "raw.nhdr")
    assert not vol.oriented
    report, _ = _render(capsys, tmp_path, tmp_path / "raw.nhdr")
    cam = Camera.from_dict(report["camera"])
    want = Camera.from_view(vol.bounds, width=16, height=16)
    np.testing.assert_allclose(cam.position, want.position, atol=1e-9)
    np.testing.assert_allclose(cam.view_up, want.view_up, atol=1e-12)
    _, err = _render(capsys, tmp_path, tmp_path / "raw.nhdr", "--view", "anterior")
    assert "records no patient orientation" in err  # a patient view of it is a guess, said so
