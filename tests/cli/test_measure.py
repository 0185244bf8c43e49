"""``dvr-perception measure``: JSON report, output figures and degenerate input (in-process)."""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from dvr_perception._files import read_png
from dvr_perception.cli import main
from dvr_perception.cli.measure import FIGURES

REQUIRED_KEYS = {
    "E_v",
    "E_s",
    "E_t",
    "seconds",
    "seconds_measures",
    "size",
    "volume",
    "structures",
    "relations",
    "undetermined",
    "notes",
}
STRUCTURE_KEYS = {
    "visible_share",
    "target_share",
    "assigned_share",
    "perceived_transparency",
    "expected_opacity",
}


def _no_nan(text: str) -> dict:
    """Parse one JSON object, refusing NaN and infinities (which JSON does not have)."""

    def refuse(token):
        raise AssertionError(f"non-finite number {token} in JSON")

    assert text.count("\n") == 1, text
    assert text.endswith("\n")
    obj = json.loads(text, parse_constant=refuse)
    assert isinstance(obj, dict)
    return obj


def _run_captured(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def phantom_run(tmp_path_factory):
    """``measure phantom --size 64 --json --out-dir DIR``, run once for the module."""
    out_dir = tmp_path_factory.mktemp("measure") / "out"
    code, out, err = _run_captured(
        ["measure", "phantom", "--size", "64", "--json", "--out-dir", str(out_dir)]
    )
    assert code == 0, err
    return _no_nan(out), out_dir


def _check_report(report: dict, names) -> None:
    assert set(report) >= REQUIRED_KEYS
    for key in ("E_v", "E_s", "E_t", "seconds", "seconds_measures"):
        assert isinstance(report[key], float), key
        assert math.isfinite(report[key]), key
    assert 0.0 <= report["E_v"] <= 2.0
    assert 0.0 <= report["E_s"] <= 1.0
    assert report["E_t"] >= 0.0
    assert 0.0 <= report["seconds_measures"] <= report["seconds"]
    assert list(report["structures"]) == list(names)
    for entry in report["structures"].values():
        assert set(entry) >= STRUCTURE_KEYS
        for key in ("visible_share", "assigned_share", "expected_opacity"):
            assert 0.0 <= entry[key] <= 1.0 + 1e-9
        alpha = entry["perceived_transparency"]
        assert alpha is None or 0.0 <= alpha <= 1.0
    for rel in report["relations"]:
        assert set(rel) == {"a", "b", "kind", "encloser"}
        assert rel["a"] in names
        assert rel["b"] in names
        assert rel["kind"] in ("separate", "touch", "enclose", "overlap")
        assert rel["encloser"] is None or rel["encloser"] in (rel["a"], rel["b"])
    assert isinstance(report["undetermined"], list)
    assert all(isinstance(n, str) for n in report["notes"])


def test_measure_phantom_json(phantom_run):
    from dvr_perception.structures.phantom import make_phantom

    report, _ = phantom_run
    _, spec = make_phantom()
    _check_report(report, spec.names)
    assert report["size"] == [64, 64]
    assert report["volume"] == "phantom"
    # the phantom's layers are nested, so some relation is an enclosure
    assert any(r["kind"] == "enclose" for r in report["relations"])
    # shares sum to 1 over the structures
    shares = report["structures"].values()
    assert sum(s["visible_share"] for s in shares) == pytest.approx(1.0, abs=1e-3)
    assert sum(s["assigned_share"] for s in shares) == pytest.approx(1.0, abs=1e-3)


def test_measure_out_dir_files(phantom_run):
    report, out_dir = phantom_run
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(FIGURES)  # no temp files left
    assert report["out_dir"] == str(out_dir)
    assert [p.rsplit("/", 1)[-1] for p in report["files"]] == list(FIGURES)
    image = read_png(out_dir / "image.png")
    assert image.shape == (64, 64, 3)
    for name in FIGURES:
        if not name.endswith(".png"):
            continue
        pixels = read_png(out_dir / name)
        assert pixels.ndim == 3, name
        assert pixels.shape[2] in (3, 4), name
        assert min(pixels.shape[:2]) >= 64, name
        colours = np.unique(pixels[..., :3].reshape(-1, 3), axis=0)
        assert len(colours) > 8, f"{name} is (nearly) a single colour"
    saved = json.loads((out_dir / "measures.json").read_text(encoding="utf-8"))
    assert saved == report


def test_measure_text_summary(capsys):
    code = main(["measure", "phantom", "--size", "32"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert out.startswith("measures of phantom (32x32")
    for key in ("E_v", "E_s", "E_t"):
        assert key in out
    assert "skin" in out
    assert len(out.splitlines()) < 30


def test_measure_bad_spec_path(capsys, tmp_path):
    out_dir = tmp_path / "never"
    missing = tmp_path / "missing.json"
    argv = ["measure", "phantom", "--structures", str(missing), "--out-dir", str(out_dir)]
    code = main([*argv, "--json"])
    out, err = capsys.readouterr()
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dvr-perception: error: ")
    assert "missing.json" in lines[0]
    assert not out_dir.exists()  # nothing is created before the inputs are checked


def test_measure_bad_bins(capsys):
    code = main(["measure", "phantom", "--bins", "0"])
    _, err = capsys.readouterr()
    assert code == 2
    assert err.strip().startswith("dvr-perception: error: ")
    assert "--bins" in err


@pytest.mark.parametrize("ext", [".nhdr", ".vti"])
def test_measure_uniform_volume(capsys, tmp_path, ext):
    """A constant volume: no structure boundary, no overlap.

    Defined behaviour: ``E_v = 0`` (one structure sees all it is assigned), ``E_t = 0`` with
    the transparency undetermined (Case 1, plain region only) and a note, and ``E_s`` is a
    number in [0, 1] coming only from the image variation (``v_s = 0``), with a note saying so.
    """
    from dvr_perception.volume import Volume, save_volume

    path = tmp_path / f"uniform{ext}"
    save_volume(Volume(np.full((16, 16, 16), 100, np.uint8)), path)
    spec = {
        "version": 1,
        "structures": [{"name": "all", "range": [50, 150], "importance": 0.5, "color": [1, 1, 1]}],
    }
    spec_path = tmp_path / "uniform_spec.json"
    spec_path.write_text(json.dumps(spec), encoding="utf-8")
    out_dir = tmp_path / "out"
    argv = ["measure", str(path), "--structures", str(spec_path), "--size", "32", "--json"]
    code = main([*argv, "--out-dir", str(out_dir)])
    out, err = capsys.readouterr()
    assert code == 0, err
    report = _no_nan(out)
    _check_report(report, ["all"])
    assert report["E_v"] == pytest.approx(0.0, abs=1e-6)
    assert report["E_t"] == 0.0
    entry = report["structures"]["all"]
    assert entry["perceived_transparency"] is None
    assert entry["visible_share"] == pytest.approx(1.0)
    assert entry["assigned_share"] == pytest.approx(1.0)
    assert report["relations"] == []
    notes = " | ".join(report["notes"])
    assert "curvature volume is 0 everywhere" in notes
    assert "no region has a determinable layer transmittance" in notes
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(FIGURES)
    saved = (out_dir / "measures.json").read_text(encoding="utf-8")
    assert "NaN" not in saved
    assert "Infinity" not in saved


def test_measure_verbose_logs_progress_inside_the_long_steps(capsys):
    code = main(["measure", "phantom", "--size", "32", "-v"])
    assert code == 0
    err = capsys.readouterr().err
    for step in ("curvature", "rays"):  # every quarter, from the library's progress callbacks
        lines = [line for line in err.splitlines() if line.startswith(f"dvr-perception: {step}: ")]
        got = [int(line.rsplit(" ", 2)[-2]) for line in lines]
        assert got == sorted(set(got)), err
        assert got[-1] == 100, err
        assert len(got) >= 2, err
        assert set(got) <= {25, 50, 75, 100}
    assert "dvr-perception: curvature: 50 %" in err  # z slices: every quarter is passed
