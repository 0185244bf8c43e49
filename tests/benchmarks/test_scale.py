"""The scale benchmark (issue 17): per-process peak RSS, and its section of the report."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from dvr_perception.cli.report import load_benchmarks

#: ``benchmarks/scale.py``: a developer tool of the checkout (not in the package).
SCALE = Path(__file__).resolve().parents[2] / "benchmarks" / "scale.py"


@pytest.fixture(scope="module")
def modules():
    spec = importlib.util.spec_from_file_location("_benchmarks_scale", SCALE)
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)
    return scale, load_benchmarks()


@pytest.mark.parametrize("mb", [50, 400])
def test_each_run_reports_its_own_peak_memory(modules, mb):
    scale, _ = modules
    code = f"import numpy as np; a = np.ones({mb} * 2**20, np.uint8); print(int(a.sum()))"
    got = scale._run([sys.executable, "-c", code])
    assert got["rc"] == 0
    assert int(got["stdout"]) == mb * 2**20
    assert mb < got["peak_rss_mb"] < mb + 150  # the interpreter and numpy: well under 150 MB


def test_a_failing_run_keeps_its_error(modules):
    scale, _ = modules
    got = scale._run([sys.executable, "-c", "import sys; sys.exit('no such volume')"])
    assert got["rc"] == 1
    assert "no such volume" in got["stderr"]


def test_the_report_renders_sizes_and_ranks(modules):
    _, report = modules
    scale = {
        "size": 512, "cpus": 2, "when": "2026-12-03 10:00",
        "sizes": [{"label": "cthead up 2,2,4", "volume": "big.nhdr", "dims": [512, 512, 452],
                   "voxels": 118489088,
                   "curvature_s": 9.5, "curvature_vtk_frames": 11.9, "frame_s": 3.1,
                   "vtk_frame_s": 0.8, "optimize_s": 17.7, "optimize_vtk_frames": 22.1,
                   "peak_rss_mb": 1500.0, "optimize_e2e_s": 19.0,
                   "optimize_e2e_peak_rss_mb": 1380.0}],
        "ranks": [{"ranks": 2, "volume": "big.nhdr", "wall_s": 30.0, "E": {"E_v": 0.5},
                   "per_rank": [{"voxels": 71093453, "peak_rss_mb": 900.0},
                                {"voxels": 47395635, "peak_rss_mb": 700.0}]}],
    }  # fmt: skip
    text = "\n".join(report._scale_section(scale, {}))
    assert "| cthead up 2,2,4 | 512\u00d7512\u00d7452 | 118.5 | 9.50 | 11.9 |" in text
    assert "| 2 | 30.0 | 60 % / 40 % | 900 / 700 | E_v 0.50000 |" in text
    assert report._scale_section(None, {}) == []
