"""``measure`` on a volume the memory limit makes bricked equals the whole-volume measure.

Under a small ``--memory-limit`` the curvature is a
:class:`~dvr_perception.rays.curvature_field.CurvatureField` (computed per brick) and the
analysis walks bricks; ``measure`` crashed there comparing the field with 0 (issue 29).
"""

from __future__ import annotations

import contextlib
import io
import json
import os

import numpy as np
import pytest

from dvr_perception.cli import main
from dvr_perception.rays import bricks, memory
from dvr_perception.structures.io import save_spec
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.volume import Volume, save_volume


def _measure(argv) -> dict:
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    finally:  # the CLI also sets the limit's variable for child processes: undo both
        memory.set_limit(None)
        os.environ.pop(memory.ENV, None)
    assert code == 0, err.getvalue()
    return json.loads(out.getvalue())


@pytest.fixture
def count_bricked(monkeypatch):
    """Count the calls of the bricked analysis (the measures' image-only re-walks apart)."""
    calls = []
    real = bricks.analyze_bricked

    def spy(*args, **kwargs):
        if kwargs.get("occlusion_free", True):  # not a re-walk of an encloser's pixels (D7)
            calls.append(kwargs.get("brick"))
        return real(*args, **kwargs)

    monkeypatch.setattr(bricks, "analyze_bricked", spy)
    return calls


def test_bricked_measure_equals_whole_measure(tmp_path, count_bricked, monkeypatch):
    monkeypatch.delenv(memory.ENV, raising=False)
    vol, spec = make_phantom(size=56)  # 8 bytes a voxel whole: over 1M, so bricks
    save_volume(vol, tmp_path / "ph.nhdr")
    save_spec(spec, tmp_path / "ph.json")
    argv = ["measure", str(tmp_path / "ph.nhdr"), "--structures", str(tmp_path / "ph.json"),
            "--size", "24", "--json"]  # fmt: skip
    whole = _measure(argv)
    assert count_bricked == []
    bricked = _measure([*argv, "--memory-limit", "1M"])
    assert len(count_bricked) == 1  # the limit made it bricked
    for key in ("E_v", "E_s", "E_t", "coverage"):
        assert bricked[key] == pytest.approx(whole[key], rel=1e-6, abs=1e-9), key
    assert whole["E_v"] > 0  # a real comparison, not of zeros
    assert whole["E_s"] > 0
    assert list(bricked["structures"]) == list(whole["structures"])
    for name, entry in whole["structures"].items():
        assert bricked["structures"][name]["visible_share"] == pytest.approx(
            entry["visible_share"], rel=1e-6, abs=1e-9
        )
    assert bricked["regions"] == whole["regions"]


def test_bricked_measure_of_a_uniform_volume_notes_zero_curvature(
    tmp_path, count_bricked, monkeypatch
):
    """No boundary: the note says v_s = 0 also when the curvature volume was never held."""
    monkeypatch.delenv(memory.ENV, raising=False)
    save_volume(Volume(np.full((56, 56, 56), 100, np.uint8)), tmp_path / "u.nhdr")
    spec = {"version": 1, "structures": [
        {"name": "all", "range": [50, 150], "importance": 0.5, "color": [1, 1, 1]}]}  # fmt: skip
    (tmp_path / "u.json").write_text(json.dumps(spec))
    report = _measure(["measure", str(tmp_path / "u.nhdr"), "--structures",
                       str(tmp_path / "u.json"), "--size", "16", "--json",
                       "--memory-limit", "1M"])  # fmt: skip
    assert len(count_bricked) == 1
    notes = " | ".join(report["notes"])
    assert "v_s = 0" in notes
    assert report["E_t"] == 0.0
