"""The benchmark report (issue 8): its check logic, and the reduced (CI) run on the real data.

The reduced run (``dvr-perception report --quick``, 128² images) regenerates the whole report
into a temporary folder and must pass every acceptance check it records in ``summary.json``:
the saturation series is monotone as the paper reports, each stage lowers its own term,
equalisation moves the visible shares toward the target shares (D1).
"""

from __future__ import annotations

import doctest
import json

import pytest

from dvr_perception.cli import main
from dvr_perception.cli.report import load_benchmarks


@pytest.fixture(scope="module")
def checks():
    load_benchmarks()
    from dvr_perception.benchmarks import checks as module

    return module


def test_check_doctests(checks):
    failures, tried = doctest.testmod(checks, optionflags=doctest.ELLIPSIS)
    assert tried > 0
    assert failures == 0


def test_monotone_rejects_a_non_monotone_series(checks):
    xs = [25, 50, 75, 100]
    assert checks.monotone("t", xs, [0.50, 0.55, 0.60, 0.65], increasing=True)["passed"]
    bad = checks.monotone("t", xs, [0.50, 0.58, 0.57, 0.65], increasing=True)
    assert not bad["passed"]
    assert "50->75" in bad["detail"]
    assert "25->50" not in bad["detail"]
    # a tie fails the strict check, passes the non-strict one
    tie = [0.5, 0.5, 0.6, 0.7]
    assert not checks.monotone("t", xs, tie, increasing=True)["passed"]
    assert checks.monotone("t", xs, tie, increasing=True, strict=False)["passed"]
    # direction matters; order of the points does not
    assert not checks.monotone("t", xs, [0.5, 0.55, 0.6, 0.65], increasing=False)["passed"]
    assert checks.monotone("t", xs[::-1], [0.65, 0.6, 0.55, 0.5], increasing=True)["passed"]
    # an undetermined value is a failure, not a pass
    assert not checks.monotone("t", xs, [0.5, None, 0.6, 0.7], increasing=True)["passed"]


def test_lowered_and_moves_toward_can_fail(checks):
    assert checks.lowered("E", 0.5, 0.4)["passed"]
    assert not checks.lowered("E", 0.5, 0.5)["passed"]  # unchanged is not lowered
    assert not checks.lowered("E", 0.5, 0.6)["passed"]
    assert not checks.lowered("E", 0.5, float("nan"))["passed"]
    assert checks.moves_toward("m", [0.9, 0.1], [0.5, 0.5], [0.2, 0.8])["passed"]
    assert not checks.moves_toward("m", [0.5, 0.5], [0.9, 0.1], [0.2, 0.8])["passed"]
    assert not checks.moves_toward("m", [0.5, 0.5], [0.5, 0.5], [0.2, 0.8])["passed"]
    assert not checks.all_passed([])
    assert not checks.all_passed([{"passed": True}, {"passed": False}])


@pytest.fixture(scope="module")
def quick_report(shared_data, vtk_can_render, tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    code = main(["report", "--data", str(shared_data), "--out", str(out), "--quick"])
    assert code == 0
    return out, json.loads((out / "summary.json").read_text(encoding="utf-8"))


@pytest.mark.slow
@pytest.mark.shared_data
@pytest.mark.vtk_render
def test_quick_report_writes_everything(quick_report):
    out, summary = quick_report
    text = (out / "REPORT.md").read_text(encoding="utf-8")
    assert text.startswith("# Benchmark report")
    assert summary["config"]["quick"] is True
    assert summary["config"]["size"] == 128
    for rel in summary["images"].values():
        png = out / rel
        assert png.is_file()
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({rel})" in text
    assert not list(out.glob("**/*.tmp*"))
    perf = summary["performance"]
    assert all(len(p) >= 3 for p in perf["image_size"].values())
    assert all(len(p) >= 3 for p in perf["volume_size"].values())


@pytest.mark.slow
@pytest.mark.shared_data
@pytest.mark.vtk_render
def test_quick_report_checks_cover_the_acceptance(quick_report):
    _, summary = quick_report
    names = [c["name"] for c in summary["checks"]]
    assert any(n.startswith("saturation series, TAP (neghip)") for n in names)
    assert any(n.startswith("saturation series (neghip)") for n in names)
    assert sum(n.startswith("equalisation ") for n in names) == 6
    for ds in ("engine", "lidc_chest"):
        for stage in ("opacity", "lighting", "colour"):
            assert any(n.startswith(f"{stage} stage lowers") and ds in n for n in names)


#: Checks of the reduced run that fail today, with why (issue 8 stays open until they hold).
#: Each must still fail: when a fix makes one pass, this test says so and it leaves the list.
KNOWN_GAPS: dict[str, str] = {
    "lighting stage lowers E_s: cthead": (
        "issue 32 (D9): E_s is read at a scale relative to the image and scaled by 3 x its "
        "mean, so it means the same at 96 and 512 px; the lighting stage then finds -1.7 to "
        "-1.9 % on the equalised head (a grid over the materials and light reaches about -4 %), "
        "where the per-pixel Sobel with a 99th-percentile scale gave -8.5 %, partly by letting "
        "a highlight rescale the whole image"
    ),
}


def _gap(name: str) -> str | None:
    return next((k for k in KNOWN_GAPS if name.startswith(k)), None)


@pytest.mark.slow
@pytest.mark.shared_data
@pytest.mark.vtk_render
def test_quick_report_checks_pass_but_the_known_gaps(quick_report):
    _, summary = quick_report
    failed = {c["name"]: c["detail"] for c in summary["checks"] if not c["passed"]}
    unexpected = [f"{n}: {d}" for n, d in failed.items() if _gap(n) is None]
    assert not unexpected, "failed report checks:\n" + "\n".join(unexpected)
    still_failing = {_gap(n) for n in failed}
    fixed = [k for k in KNOWN_GAPS if k not in still_failing]
    assert not fixed, f"now passing, remove from KNOWN_GAPS: {fixed}"
    assert summary["all_passed"] is (not failed)


def test_report_rejects_a_data_folder_without_the_volumes(tmp_path, capsys):
    code = main(["report", "--data", str(tmp_path), "--out", str(tmp_path / "out"), "--quick"])
    assert code == 2
    err = capsys.readouterr().err
    assert "cthead.nhdr" in err
    assert not (tmp_path / "out").exists()


def test_markdown_only_needs_a_summary(tmp_path, capsys):
    assert main(["report", "--markdown-only", "--out", str(tmp_path)]) == 2
    assert "summary.json" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.shared_data
@pytest.mark.vtk_render
def test_markdown_only_rewrites_the_same_report(quick_report, capsys):
    out, _ = quick_report
    report = out / "REPORT.md"
    before = report.read_text(encoding="utf-8")
    report.unlink()
    assert main(["report", "--markdown-only", "--out", str(out)]) == 0
    capsys.readouterr()
    assert report.read_text(encoding="utf-8") == before


def _fake_data(tmp_path):
    data = tmp_path / "data"
    data.mkdir(parents=True)
    for n in ("cthead", "engine", "neghip", "lidc_chest"):
        (data / f"{n}.nhdr").write_text("NRRD0004\n")
    return data


def test_a_failed_report_leaves_the_folder_as_it_was(tmp_path, capsys, monkeypatch):
    """Staged: figures in images/ and the summary appear all together or not at all."""
    report = load_benchmarks()
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / "old.png").write_bytes(b"old")
    (out / "scale.json").write_text("{}")

    def build(cfg, folder, *, log, final):
        assert final == out
        assert folder != out  # written into a staging folder
        (folder / "images").mkdir()
        (folder / "images" / "fig.png").write_bytes(b"new")
        (folder / "summary.json").write_text("{}")
        raise KeyboardInterrupt  # Ctrl-C in the middle of the run

    monkeypatch.setattr(report, "build", build)
    argv = ["report", "--data", str(_fake_data(tmp_path)), "--out", str(out), "--quick"]
    assert main(argv) == 130
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        "images", "images/old.png", "scale.json"
    ]  # fmt: skip

    def build_ok(cfg, folder, *, log, final):
        (folder / "images").mkdir()
        (folder / "images" / "fig.png").write_bytes(b"new")
        (folder / "summary.json").write_text("{}")
        return {"checks": [], "seconds": 1.0, "all_passed": True}

    monkeypatch.setattr(report, "build", build_ok)
    assert main(["report", "--data", str(_fake_data(tmp_path / "b")), "--out", str(out)]) == 0
    assert (out / "images" / "fig.png").read_bytes() == b"new"
    assert (out / "images" / "old.png").read_bytes() == b"old"  # other files stay
    assert (out / "summary.json").is_file()
    capsys.readouterr()


def test_a_second_report_into_the_same_folder_is_refused(tmp_path, capsys, monkeypatch):
    report = load_benchmarks()
    out = tmp_path / "out"
    data = _fake_data(tmp_path)

    def build(cfg, folder, *, log, final):
        assert main(["report", "--data", str(data), "--out", str(out), "--quick"]) == 2
        raise RuntimeError("stop")

    monkeypatch.setattr(report, "build", build)
    assert main(["report", "--data", str(data), "--out", str(out), "--quick"]) == 1
    err = capsys.readouterr().err
    assert "another dvr-perception run" in err
    assert "stop" in err
    assert not out.exists()  # the folder the failed run created is gone again
