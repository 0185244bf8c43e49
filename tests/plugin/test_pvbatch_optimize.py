"""``dvr-perception pvbatch VOLUME --optimize`` against ``dvr-perception optimize`` (issue 19).

One pvbatch run (ParaView's *Optimize Transfer Function* on the engine data, with ParaView's
before/after renderings, the preset and ``result.json``) and one library run of the same view,
stages and iterations, at a small size so that both fit CI's time budget.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception._files import read_png
from tests.plugin.conftest import assert_no_vtk_messages

SIZE = 32
#: The same optimisation on both sides (small: about 15 s each on two shared cores).
ARGS = ["--size", str(SIZE), "--view=30,20", "--stages", "opacity", "--max-iter", "2",
        "--resolution", "32"]  # fmt: skip
TERMS = ("E_v", "E_s", "E_t", "E")


@pytest.fixture(scope="module")
def engine(shared_data):
    return shared_data / "engine.nhdr"


def test_pvbatch_optimize_matches_the_library_and_writes_paraview_files(
    paraview, engine, tmp_path, capsys
):
    from dvr_perception.cli import main

    pv_out, lib_out = tmp_path / "pv", tmp_path / "lib"
    assert main(["pvbatch", str(engine), "--optimize", *ARGS, "--out", str(pv_out), "-v"]) == 0
    assert_no_vtk_messages(capsys.readouterr().err)  # -v: ParaView's own output on stderr
    assert main(["optimize", str(engine), *ARGS, "--out", str(lib_out), "--json"]) == 0
    lib = json.loads(capsys.readouterr().out)
    pv = json.loads((pv_out / "result.json").read_text())
    print("seconds: pvbatch", pv["seconds"], "library", lib["seconds"])
    # the same scene: initial terms equal, final E within 2 % (measured equal to ~1e-7)
    for key, value in lib["camera"].items():
        assert np.allclose(pv["camera"][key], value, rtol=0, atol=1e-9), key
    for k in TERMS:
        assert pv["initial"][k] == pytest.approx(lib["initial"][k], abs=1e-5), k
    assert pv["final"]["E"] == pytest.approx(lib["final"]["E"], rel=0.02)
    assert pv["final"]["E"] <= pv["initial"]["E"] + 1e-9
    # ParaView's renderings before and after, the preset and the spec
    before, after = read_png(pv_out / "before.png"), read_png(pv_out / "after.png")
    assert before.shape[:2] == after.shape[:2] == (SIZE, SIZE)
    assert before[..., :3].max() > 8
    assert after[..., :3].max() > 8
    assert not np.array_equal(before, after)  # the optimised transfer function was applied
    (preset,) = json.loads((pv_out / "optimized_preset.json").read_text())
    assert {"Name", "RGBPoints", "Points", "ColorSpace"} <= set(preset)
    assert len(preset["Points"]) % 4 == 0
    assert {"before.png", "after.png", "optimized_preset.json", "result.json"} <= set(pv["files"])
