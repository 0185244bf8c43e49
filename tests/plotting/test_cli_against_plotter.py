"""``check-renderer --against plotter``: same JSON keys as against VTK's mappers."""

from __future__ import annotations

import json

import pytest

from dvr_perception._files import read_png
from dvr_perception.cli import main


@pytest.mark.vtk_render
def test_check_renderer_against_plotter(capsys, tmp_path, vtk_can_render):
    argv = ["check-renderer", "phantom", "--size", "96", "--against", "plotter"]
    code = main([*argv, "--out-dir", str(tmp_path), "--json"])
    out = capsys.readouterr().out
    assert code == 0
    report = json.loads(out.strip().splitlines()[-1])
    for key in ("ssim", "mean_abs_diff", "ours_png", "vtk_png", "diff_png", "mapper", "size"):
        assert key in report
    assert report["mapper"] == "plotter"
    assert report["ssim"] >= 0.93
    assert read_png(report["vtk_png"]).shape == (96, 96, 3)
