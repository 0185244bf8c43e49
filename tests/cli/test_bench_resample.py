"""``bench --resample`` / ``--save-volume`` and the peak memory in its report."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest

from dvr_perception.cli import main
from dvr_perception.cli._common import parse_factors
from dvr_perception.errors import DVRInputError
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.structures.io import save_spec
from dvr_perception.volume import Volume, load_volume, save_volume
from dvr_perception.volume.resample import upsample


@pytest.fixture
def small_scene(tmp_path, monkeypatch):
    """A 10x12x14 (x, y, z) ball and its spec; VTK's frame timer replaced (no OpenGL needed)."""
    from dvr_perception.rays import vtk_process, vtk_reference

    z, y, x = np.mgrid[:14, :12, :10].astype(np.float64)
    r = np.sqrt((x - 4.5) ** 2 + (y - 5.5) ** 2 + (z - 6.5) ** 2)
    vol = Volume((200 / (1 + np.exp(r - 4))).astype(np.uint8), spacing=(1.0, 1.0, 2.0))
    save_volume(vol, tmp_path / "ball.nhdr")
    spec = StructureSpec((Structure("ball", 0.5, (1.0, 0.5, 0.5), range=(100.0, 255.0)),))
    save_spec(spec, tmp_path / "ball.json")

    @contextlib.contextmanager
    def timer(*_):
        yield lambda: 0.25

    monkeypatch.setattr(vtk_reference, "vtk_frame_timer", timer)
    monkeypatch.setattr(vtk_process, "vtk_frame_process", timer)
    return tmp_path


def _bench(capsys, argv):
    code = main(["bench", *argv, "--size", "12", "--repeat", "1", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def test_resample_gives_the_expected_shape_and_reports_memory(capsys, small_scene):
    vol = str(small_scene / "ball.nhdr")
    spec = str(small_scene / "ball.json")
    saved = small_scene / "big.nhdr"
    report = _bench(
        capsys,
        [vol, "--structures", spec, "--resample", "2,3,1", "--save-volume", str(saved)],
    )
    assert report["dims"] == [20, 36, 14]
    assert report["resample"] == [2, 3, 1]
    assert report["peak_rss_mb"] > 0
    assert report["curvature_vtk_frames"] == pytest.approx(report["curvature_s"] / 0.25)
    big = load_volume(saved)
    assert big.dims == (20, 36, 14)
    assert big.spacing == pytest.approx((0.5, 1.0 / 3, 2.0))
    plain = _bench(capsys, [vol, "--structures", spec])
    assert plain["dims"] == [10, 12, 14]
    assert plain["resample"] is None
    assert plain["peak_rss_mb"] > 0


def test_parse_factors():
    assert parse_factors("2,2,4") == (2, 2, 4)
    assert parse_factors(" 3 ") == (3, 3, 3)
    for bad in ("0", "2,2", "a,b,c", "1,1,65"):
        with pytest.raises(DVRInputError, match="--resample"):
            parse_factors(bad)


def test_bad_resample_fails_before_loading(capsys):
    code = main(["bench", "no_such_file.nhdr", "--resample", "2x2"])
    _, err = capsys.readouterr()
    assert code == 2
    assert "--resample" in err


def test_upsample_is_trilinear_and_keeps_world_extent():
    data = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)  # linear in each index
    vol = Volume(data, spacing=(1.0, 2.0, 3.0), origin=(1.0, 2.0, 3.0))
    big = upsample(vol, (2, 3, 4))
    assert big.data.shape == (12, 12, 10)
    assert big.spacing == pytest.approx((0.5, 2 / 3, 0.75))
    # voxel i sits at old index (i + 0.5) / f - 0.5: a linear field is reproduced inside
    zi = (np.arange(12) + 0.5) / 4 - 0.5
    yi = (np.arange(12) + 0.5) / 3 - 0.5
    xi = (np.arange(10) + 0.5) / 2 - 0.5
    want = 20 * zi[:, None, None] + 5 * yi[None, :, None] + xi[None, None, :]
    inside = (slice(2, -2), slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(big.data[inside], want[inside], atol=1e-4)
    # the world position of the first new voxel is that old index
    assert big.origin == pytest.approx((0.75, 2.0 - 2 / 3, 3.0 - 9 / 8))
    labels = np.arange(8, dtype=np.uint8).reshape(2, 2, 2)
    lab = upsample(Volume(np.zeros((2, 2, 2), np.uint8), labels=labels), 2).labels
    np.testing.assert_array_equal(lab[::2, ::2, ::2], labels)
    np.testing.assert_array_equal(lab[1::2, 1::2, 1::2], labels)
    with pytest.raises(DVRInputError, match="factors"):
        upsample(vol, (1, 0, 1))


def test_save_volume_that_another_run_writes_is_refused(capsys, small_scene):
    from dvr_perception._files import file_lock

    saved = small_scene / "big.nhdr"
    argv = [str(small_scene / "ball.nhdr"), "--structures", str(small_scene / "ball.json")]
    with file_lock(saved):  # another bench is writing that file
        code = main(["bench", *argv, "--size", "12", "--save-volume", str(saved)])
        err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1, err
    assert f"output file {saved}: another dvr-perception run" in err[0]
    assert not saved.exists()
    assert not (small_scene / ".big.nhdr.lock").exists()  # released by its holder
    _bench(capsys, [*argv, "--save-volume", str(saved)])  # free again: it is written
    assert load_volume(saved).dims == (10, 12, 14)
    assert not (small_scene / ".big.nhdr.lock").exists()
