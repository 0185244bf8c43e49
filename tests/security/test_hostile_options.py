"""Size-like command-line options are bounded or counted against the memory limit (issue 29).

Every option that sizes an array, a loop or a set of processes (``--bins``, ``--size``,
``--repeat``, ``--resample``, ``--resolution``, ``--max-iter``, ``--views``, ``--ranks``,
``--sigma``, ``--phantom-size``, ``--iterations``) fails at once with one error naming the
option, within the hostile-input bounds (10 s, 400 MB) and writing nothing.
``--bins 150000000`` took 1.4 GB before and then an unexpected MemoryError.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dvr_perception.cli.bench import MAX_REPEAT
from dvr_perception.cli.measure import MAX_BINS
from dvr_perception.cli.optimize import MAX_ITER, MAX_RESOLUTION, MAX_VIEWS
from dvr_perception.cli.pvbatch import MAX_RANKS, MAX_SIGMA

SMALL_NHDR = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 32 32 32\nendian: little\n"
OPT = ["--stages", "opacity"]

#: name -> (argv, needles); argv may use {vol} (a 32³ volume) and runs in an empty folder.
CASES = {
    "bins-huge": (["measure", "phantom", "--bins", "150000000", "--out-dir", "o"],
                  ["--bins", f"1 to {MAX_BINS}", "150000000"]),
    "bins-one-over": (["measure", "phantom", "--bins", str(MAX_BINS + 1)], ["--bins"]),
    "bins-digits": (["measure", "phantom", "--bins", "9" * 5000], ["--bins", "5000 characters"]),
    "repeat-huge": (["bench", "--repeat", "1000000000"],
                    ["--repeat", f"at most {MAX_REPEAT}"]),
    "resample-huge": (["bench", "{vol}", "--resample", "64", "--memory-limit", "64M"],
                      ["--resample 64", "2048x2048x2048", "memory limit"]),
    "resample-axes": (["bench", "{vol}", "--resample", "1,64,64", "--memory-limit", "64M"],
                      ["--resample 1,64,64", "32x2048x2048"]),
    "size-vs-limit": (["measure", "phantom", "--size", "16384", "--memory-limit", "64M"],
                      ["--size", "memory limit"]),
    "demo-size": (["demo", "--size", "16384", "--out", "d"], ["--size", "memory limit"]),
    "resolution": (["optimize", "phantom", "--resolution", "100000", "--out", "o"],
                   ["--resolution", str(MAX_RESOLUTION)]),
    "max-iter": (["optimize", "phantom", "--max-iter", "100000", "--out", "o"],
                 ["--max-iter", str(MAX_ITER)]),
    "views": (["optimize", "phantom", "--views", "1000", "--out", "o"],
              ["--views", str(MAX_VIEWS)]),
    "pv-ranks": (["pvbatch", "phantom", "--ranks", "100000", "--out", "o"],
                 ["--ranks", f"1 to {MAX_RANKS}"]),
    "pv-sigma": (["pvbatch", "phantom", "--sigma", "1e9", "--out", "o"],
                 ["--sigma", f"at most {MAX_SIGMA:g}"]),
    "pv-max-iter": (["pvbatch", "phantom", "--optimize", "--max-iter", "100000", "--out", "o"],
                    ["--max-iter", str(MAX_ITER)]),
    "pv-resolution": (["pvbatch", "phantom", "--optimize", "--resolution", "100000", "--out",
                       "o"], ["--resolution", str(MAX_RESOLUTION)]),
    "pv-timeout": (["pvbatch", "phantom", "--timeout", "inf", "--out", "o"], ["--timeout"]),
    "app-phantom": (["app", "--phantom-size", "100000"], ["--phantom-size", "512"]),
    "app-iterations": (["app", "--iterations", "100000"], ["--iterations", "200"]),
}  # fmt: skip


@pytest.fixture(scope="module")
def results(tmp_path_factory, batch):
    root = tmp_path_factory.mktemp("options")
    vol = root / "vol.nhdr"
    (root / "vol.raw").write_bytes(bytes(range(256)) * 128)  # 32³ voxels
    vol.write_text(SMALL_NHDR + "encoding: raw\ndata file: vol.raw\n")
    calls, runs = [], {}
    for name, (argv, _) in CASES.items():
        run = root / name
        run.mkdir()
        runs[name] = run
        argv = [a.replace("{vol}", str(vol)) for a in argv]
        calls.append({"argv": argv, "cwd": str(run), "env": {}})
    out = batch(calls, root)
    return {name: (runs[name], r) for name, r in zip(CASES, out, strict=True)}


@pytest.mark.parametrize("name", list(CASES))
def test_size_like_option_fails_at_once_naming_it(results, name):
    run, result = results[name]
    result.one_error(*CASES[name][1])
    assert sorted(p.name for p in run.iterdir()) == []  # no folder, lock or staging left


def test_bins_at_the_bound_measure(capsys, tmp_path):
    """``--bins`` at its largest still measures and draws the histograms."""
    from dvr_perception.cli import main

    out = tmp_path / "m"
    code = main(["measure", "phantom", "--size", "16", "--bins", str(MAX_BINS), "--json",
                 "--out-dir", str(out)])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    report = json.loads(captured.out)
    assert report["E_v"] >= 0
    assert Path(out / "visibility_histograms.png").stat().st_size > 0
