"""``dvr-perception optimize`` on the phantom: files, JSON, presets, Ctrl-C and bad input."""

from __future__ import annotations

import contextlib
import io
import json
import re
import signal

import pytest

from dvr_perception._files import read_png
from dvr_perception.cli import main
from dvr_perception.cli import optimize as optimize_cmd
from dvr_perception.cli._plots import MEASURE_FIGURES

FILES = {
    "before.png",
    "after.png",
    "before_after.png",
    "convergence.png",
    "optimized_spec.json",
    "paraview_preset.json",
    "slicer.vp.json",
    "result.json",
    *(f"{p}_{f}" for p in ("before", "after") for f in MEASURE_FIGURES),
}
TERM_KEYS = {"E_v", "E_s", "E_t", "E"}
#: The measures' names and status codes, which the default text never uses.
JARGON = re.compile(r"\bE_[vst]\b|\bE\b|Eq\. ?13|\bS \(|status \d|max_iter|StopIteration")
STRUCTURE_KEYS = {
    "visible_share",
    "target_share",
    "assigned_share",
    "perceived_transparency",
    "expected_opacity",
}


def _run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _one_json(out: str) -> dict:
    assert out.count("\n") == 1, out
    return json.loads(out)


def _check_report(report, out_dir, stages):
    for key in ("initial", "final", "stages", "seconds", "status", "files"):
        assert key in report
    for key in ("initial", "final"):
        assert set(report[key]) >= TERM_KEYS
        assert report[key]["structures"]
        for entry in report[key]["structures"].values():
            assert set(entry) >= STRUCTURE_KEYS
    assert [s["name"] for s in report["stages"]] == list(stages)
    for s in report["stages"]:
        assert {"name", "before", "after", "iterations", "seconds"} <= set(s)
        assert set(s["before"]) >= TERM_KEYS
        assert set(s["after"]) >= TERM_KEYS
    assert report["final"]["E"] <= report["initial"]["E"] + 1e-9
    assert {p.name for p in out_dir.iterdir()} == FILES
    assert sorted(report["files"]) == sorted(str(out_dir / f) for f in FILES)
    assert json.loads((out_dir / "result.json").read_text())["final"] == report["final"]


@pytest.fixture(scope="module")
def opacity_run(tmp_path_factory):
    """One ``--stages opacity`` run at 48 px (shared by the tests below)."""
    out_dir = tmp_path_factory.mktemp("opt") / "out"
    stdout, stderr = io.StringIO(), io.StringIO()
    argv = ["optimize", "phantom", "--size", "48", "--stages", "opacity", "--max-iter", "3"]
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main([*argv, "--out", str(out_dir), "--json"])
    return code, stdout.getvalue(), stderr.getvalue(), out_dir


def test_opacity_stage_json_and_files(opacity_run):
    code, out, err, out_dir = opacity_run
    assert code == 0, err
    report = _one_json(out)
    _check_report(report, out_dir, ["opacity"])
    assert read_png(out_dir / "before.png").shape == (48, 48, 3)
    assert read_png(out_dir / "after.png").shape == (48, 48, 3)
    assert "opacity" in err
    assert "[" in err


def test_optimized_spec_renders_and_presets_parse(capsys, opacity_run, tmp_path):
    _, _, _, out_dir = opacity_run
    spec = out_dir / "optimized_spec.json"
    png = tmp_path / "r.png"
    code, out, err = _run(
        capsys, ["render", "phantom", "--structures", str(spec), "--size", "48", "--out", str(png)]
    )
    assert code == 0, err
    after = read_png(out_dir / "after.png")
    assert (read_png(png) == after).all()
    code, out, err = _run(
        capsys, ["measure", "phantom", "--structures", str(spec), "--size", "48", "--json"]
    )
    assert code == 0, err
    report = json.loads((out_dir / "result.json").read_text())
    assert _one_json(out)["E_v"] == pytest.approx(report["final"]["E_v"], abs=1e-9)
    preset = json.loads((out_dir / "paraview_preset.json").read_text())
    assert preset  # a list (ParaView) or an object
    vp = json.loads((out_dir / "slicer.vp.json").read_text())
    assert "volumeProperties" in vp


def test_three_stages(capsys, tmp_path):
    out_dir = tmp_path / "full"
    code, out, err = _run(
        capsys, ["optimize", "phantom", "--size", "48", "--out", str(out_dir), "--json"]
    )
    assert code == 0, err
    _check_report(_one_json(out), out_dir, ["opacity", "lighting", "colour"])


def test_text_summary_views_and_region(capsys, tmp_path):
    argv = ["optimize", "phantom", "--size", "40", "--stages", "opacity", "--max-iter", "2"]
    code, out, err = _run(capsys, [*argv, "--views", "2", "--out", str(tmp_path / "v")])
    assert code == 0, err
    assert "mismatch with the intended picture (lower is better): visibility" in out
    assert "what changed and why:" in out
    assert not JARGON.search(out), out
    code, out, err = _run(
        capsys, [*argv, "-v", "--region", "5,5,30,30", "--out", str(tmp_path / "r")]
    )
    assert code == 0, err
    assert "before" in out
    assert "after" in out
    assert re.search(r"status \d: ", out)
    assert json.loads((tmp_path / "r" / "result.json").read_text())["region"] == [5, 5, 30, 30]


def test_default_text_is_plain_and_explains_shading_and_colour(capsys, tmp_path):
    """All three stages: the default text (and the progress bar) names no measure and no
    status code, and says how each structure's shading and colour changed; ``-v`` adds the
    measures, Eq. 13's S and the status code; ``--json`` holds both."""
    argv = ["optimize", "phantom", "--size", "40", "--max-iter", "3"]
    code, out, err = _run(capsys, [*argv, "--out", str(tmp_path / "plain")])
    assert code == 0, err
    assert not JARGON.search(out), out
    assert not JARGON.search(err), err
    assert "\n      shading: " in out
    assert "\n      colour: " in out
    assert "finished: " in out or "stopped at the step limit" in out
    report = json.loads((tmp_path / "plain" / "result.json").read_text())
    assert {"E_v", "E_s", "E_t", "E", "S"} <= set(report["optimizer"]["final"])
    assert report["status"] in (0, 2)
    for name, e in report["structures"].items():
        assert e["lines"][0].startswith(f"{name}: opacity ")
        assert e["line"] == "; ".join(e["lines"])
        assert e["line"] in out.replace("\n      ", "; ")
    code, out, err = _run(capsys, [*argv, "-v", "--out", str(tmp_path / "verbose")])
    assert code == 0, err
    for word in ("E_v", "E_s", "E_t", "S (Eq. 13)", "[E_s on its pixels"):
        assert word in out
    assert re.search(r"status \d: ", out)
    assert "E_v" in err


def test_ctrl_c_saves_best_so_far(capsys, tmp_path, monkeypatch):
    draw = optimize_cmd.Progress.draw

    def interrupting_draw(self, info):
        draw(self, info)
        if info.nit == 1:
            signal.raise_signal(signal.SIGINT)  # what Ctrl-C does

    monkeypatch.setattr(optimize_cmd.Progress, "draw", interrupting_draw)
    handler = signal.getsignal(signal.SIGINT)
    out_dir = tmp_path / "stopped"
    argv = ["optimize", "phantom", "--size", "40", "--stages", "opacity,lighting"]
    code, out, err = _run(capsys, [*argv, "--out", str(out_dir), "--json"])
    assert code == 0, err
    report = _one_json(out)
    assert report["status"] == 1
    assert len(report["stages"]) == 1
    assert (out_dir / "optimized_spec.json").is_file()
    assert signal.getsignal(signal.SIGINT) is handler  # restored


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--weights", "0,0,0"], "--weights"),
        (["--weights", "1,-1,1"], "--weights"),
        (["--weights", "1,1"], "--weights"),
        (["--stages", "opacity,shine"], "unknown stage"),
        (["--region", "100,100,200,200"], "--region"),
        (["--region", "10,10,10,20"], "--region"),
        (["--region", "1,2,3"], "--region"),
        (["--region", "5,5,20,20", "--views", "2"], "--region"),
        (["--views", "0"], "--views"),
        (["--seed", "-1"], "seed"),
        (["--coverage-keep", "1.5"], "--coverage-keep"),
        (["--objective", "squares"], "--objective"),
        (["--memory-limit", "lots"], "--memory-limit"),
        (["--memory-limit", "1M"], "--memory-limit"),  # cannot fit: refused before the run
    ],
)
def test_bad_input_exits_2(capsys, tmp_path, option, message, monkeypatch):
    from dvr_perception import _memory as memory

    monkeypatch.setattr(memory, "_LIMIT", [None])  # --memory-limit's settings are undone
    monkeypatch.setenv(memory.ENV, "")  # after the test
    argv = ["optimize", "phantom", "--size", "32", "--out", str(tmp_path / "o"), *option]
    code, out, err = _run(capsys, argv)
    assert code == 2
    assert out == ""
    assert err.count("\n") == 1
    assert err.startswith("dvr-perception: error:")
    assert message in err


def test_coverage_keep_lets_the_opacity_stage_fade_only_that_far(capsys, tmp_path):
    argv = ["optimize", "phantom", "--size", "48", "--stages", "opacity", "--max-iter", "3"]
    code, _out, err = _run(capsys, [*argv, "--coverage-keep", "0.7", "--out", str(tmp_path / "o")])
    assert code == 0, err
    rep = json.loads((tmp_path / "o" / "result.json").read_text())
    before, after = rep["initial"]["coverage"], rep["final"]["coverage"]
    assert after >= 0.7 * before - 0.01


def test_least_squares_objective_reports_S_and_never_raises_it(capsys, tmp_path):
    argv = ["optimize", "phantom", "--size", "40", "--stages", "opacity", "--max-iter", "2"]
    out_dir = tmp_path / "ls"
    code, out, err = _run(capsys, [*argv, "--objective", "least_squares", "--out", str(out_dir)])
    assert code == 0, err
    assert "judged by each pixel's mismatch, squared (least squares)" in out
    assert not JARGON.search(out), out
    code, out, err = _run(capsys, [*argv, "-v", "--objective", "least_squares", "--out",
                                   str(tmp_path / "ls_v")])  # fmt: skip
    assert code == 0, err
    assert "S (Eq. 13)" in out
    rep = json.loads((out_dir / "result.json").read_text())
    assert rep["objective"] == "least_squares"
    assert rep["optimizer"]["final"]["S"] <= rep["optimizer"]["initial"]["S"] + 1e-12
