"""VTK's reference frames in a child process (``rays.vtk_process``)."""

import sys

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.vtk_process import vtk_frame_process
from dvr_perception.structures.spec import Structure, StructureSpec
from dvr_perception.volume.volume import Volume


def _scene(labels=None):
    vol = Volume(np.arange(12**3, dtype=np.uint16).reshape(12, 12, 12) % 200, labels=labels)
    spec = StructureSpec((Structure("a", 0.5, (1, 1, 1), range=(50, 150)),))
    return vol, spec, Camera.from_view(vol.bounds, width=16, height=16)


def test_a_child_that_cannot_start_is_one_clear_error(monkeypatch):
    monkeypatch.setattr(sys, "executable", "/bin/false")
    with (
        pytest.raises(DVRInputError, match=r"process ended \(exit code 1\)"),
        vtk_frame_process(*_scene()),
    ):
        pass


def test_the_child_reads_the_same_scene_renders_and_reports_its_memory(tmp_path, vtk_can_render):
    from dvr_perception.rays import vtk_process

    labels = (np.arange(12**3).reshape(12, 12, 12) % 3).astype(np.uint8)
    vol, spec, cam = _scene(labels)
    vol = Volume(vol.data, (0.5, 1.0, 2.0), (1.0, -2.0, 3.0), labels=labels)
    vtk_process._write_inputs(tmp_path, vol, spec, cam)
    got_vol, got_spec, got_cam = vtk_process._read_inputs(tmp_path)
    np.testing.assert_array_equal(got_vol.data, vol.data)
    np.testing.assert_array_equal(got_vol.labels, labels)
    assert (got_vol.spacing, got_vol.origin) == (vol.spacing, vol.origin)
    assert got_spec == spec
    assert got_cam.to_dict() == cam.to_dict()
    # the child renders warm frames and reports its peak memory once it has ended
    with vtk_frame_process(vol, spec, cam) as frame:
        times = [frame(), frame()]
        assert frame.peak_rss_mb is None
    assert min(times) > 0
    assert frame.peak_rss_mb > 30  # a Python with VTK loaded
