"""``dvr-perception pvbatch VOLUME --optimize [--ranks N]``: the optimiser inside ParaView.

With several ranks every rank keeps the cache entries of its piece, rank 0 runs the optimiser
and every evaluation broadcasts the parameters and composites the ranks' re-evaluations in view
order (``dvr_perception.distributed.RankSession``).  The initial E terms equal those of
``dvr-perception optimize`` on the same view within 1e-5 and the final E is within 2 % of it
(issues 17 and 19); no rank holds the whole volume.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception.cli import main
from tests.plugin.conftest import CROSS_ENV_ABS

SIZE = 64
MAX_ITER = 3
#: Below the image size: the optimiser evaluates on a second, smaller view (two caches).
RESOLUTION = 32
TERMS = ("E_v", "E_s", "E_t", "E")
_REFERENCE: dict = {}


def _scene(shared_data):
    from tests.plugin.test_mpi_ranks import REPO

    return shared_data / "neghip.nhdr", REPO / "state_files" / "neghip.json"


def _reference(shared_data, tmp_path_factory) -> dict:
    """``dvr-perception optimize`` on the same view (the pip environment), once."""
    if not _REFERENCE:
        volume, spec = _scene(shared_data)
        out = tmp_path_factory.mktemp("optimize_ref")
        argv = ["optimize", str(volume), "--structures", str(spec), "--size", str(SIZE)]
        argv += ["--max-iter", str(MAX_ITER), "--resolution", str(RESOLUTION)]
        assert main([*argv, "--out", str(out)]) == 0
        _REFERENCE.update(json.loads((out / "result.json").read_text(encoding="utf-8")))
    return _REFERENCE


@pytest.mark.slow
@pytest.mark.parametrize("ranks", [1, 2, 4])
def test_pvbatch_optimize_equals_the_optimize_command(
    mpiexec, shared_data, tmp_path, tmp_path_factory, ranks
):
    ref = _reference(shared_data, tmp_path_factory)
    volume, spec = _scene(shared_data)
    out = tmp_path / "out"
    argv = ["pvbatch", str(volume), "--structures", str(spec), "--size", str(SIZE), "--optimize"]
    argv += ["--max-iter", str(MAX_ITER), "--resolution", str(RESOLUTION)]
    argv += ["--ranks", str(ranks), "--timeout", "900"]
    assert main([*argv, "--out", str(out)]) == 0
    got = json.loads((out / "result.json").read_text(encoding="utf-8"))
    for key in TERMS:
        assert got["initial"][key] == pytest.approx(
            ref["optimizer"]["initial"][key], abs=CROSS_ENV_ABS
        ), key
    assert got["final"]["E"] == pytest.approx(ref["final"]["E"], rel=0.02)
    assert got["final"]["E"] < got["initial"]["E"]  # it optimised
    files = set(got["files"])
    assert {"before.png", "after.png", "optimized_spec.json", "result.json", "image.png"} <= files
    for name in files:
        assert (out / name).is_file(), name
    spec_out = json.loads((out / "optimized_spec.json").read_text(encoding="utf-8"))
    assert spec_out == got["optimized_spec"]
    if ranks == 1:
        assert "ranks" not in got
        return
    records = got["ranks"]
    assert [r["rank"] for r in records] == list(range(ranks))
    assert sorted(r["order"] for r in records) == list(range(ranks))
    assert len({r["evaluations"] for r in records}) == 1  # every rank in every evaluation
    assert records[0]["evaluations"] > 10
    assert {r["views"] for r in records} == {2}  # the user's view and the optimiser's
    whole = 64**3
    for r in records:
        assert r["voxels"] / whole <= {2: 0.60, 4: 0.35}[ranks], r
        assert r["peak_rss_mb"] > 0
    assert np.sum([r["voxels"] for r in records]) < 2 * whole


def test_pvbatch_optimize_bad_options_are_one_error(tmp_path, capsys):
    argv = ["pvbatch", "phantom", "--optimize", "--out", str(tmp_path / "o")]
    assert main([*argv, "--stages", "opacity,nope"]) == 2
    assert "--stages: unknown stage(s) nope" in capsys.readouterr().err
    assert main([*argv, "--weights", "1,-1,1"]) == 2
    assert "--weights" in capsys.readouterr().err
    assert main([*argv, "--timeout", "0"]) == 2
    assert "--timeout: expected a positive number of seconds" in capsys.readouterr().err
