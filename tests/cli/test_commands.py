"""The CLI commands on the phantom: render, demo, check-renderer, bench (run in-process)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception._files import read_png
from dvr_perception.cli import main

BUFFER_KEYS = {
    "rgba",
    "image",
    "accumulated",
    "visible",
    "assigned",
    "visible_share",
    "assigned_share",
    "present",
    "curvature",
    "names",
    "camera",
}


def _run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _one_json(out: str) -> dict:
    assert out.count("\n") == 1, out
    assert out.endswith("\n")
    obj = json.loads(out)
    assert isinstance(obj, dict)
    return obj


def test_render_phantom_png_and_buffers(capsys, tmp_path):
    png, npz = tmp_path / "p.png", tmp_path / "p.npz"
    argv = ["render", "phantom", "--size", "64", "--out", str(png), "--buffers", str(npz)]
    code, out, err = _run(capsys, [*argv, "--json"])
    assert code == 0, err
    report = _one_json(out)
    assert report["size"] == [64, 64]
    assert report["out"] == str(png)
    image = read_png(png)
    assert image.shape == (64, 64, 3)
    assert image.max() > 0  # the phantom is visible
    with np.load(npz) as data:
        assert set(data.files) == BUFFER_KEYS
        k = len(data["names"])
        assert k == len(report["structures"]) >= 1
        assert data["rgba"].shape == (64, 64, 4)
        assert data["image"].shape == (64, 64, 3)
        assert data["accumulated"].shape == (64, 64)
        assert data["visible"].shape == (k, 64, 64)
        assert data["assigned"].shape == (k, 64, 64)
        assert data["present"].shape == (64, 64)
        cam = json.loads(str(data["camera"]))
        assert (cam["width"], cam["height"]) == (64, 64)
        # the PNG is the quantised image buffer
        np.testing.assert_allclose(image / 255.0, data["image"], atol=0.5 / 255 + 1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.npz", "p.png"]


def test_render_non_square_and_text_output(capsys, tmp_path):
    png = tmp_path / "wide.png"
    code, out, _ = _run(capsys, ["render", "phantom", "--size", "48x32", "--out", str(png)])
    assert code == 0
    assert out.startswith(f"wrote {png}")
    assert read_png(png).shape == (32, 48, 3)


def test_camera_looking_away_warns_and_renders_black(capsys, tmp_path):
    from dvr_perception.structures.phantom import make_phantom

    volume, _ = make_phantom()
    c = volume.center
    far = 4.0 * max(volume.bounds[1::2]) + 10.0
    cam = {
        "position": [c[0], c[1], c[2] + far],
        "focal_point": [c[0], c[1], c[2] + 2 * far],  # looking away, along +z
        "width": 32,
        "height": 32,
    }
    (tmp_path / "away.json").write_text(json.dumps(cam))
    png = tmp_path / "away.png"
    code, _, err = _run(
        capsys, ["render", "phantom", "--camera", str(tmp_path / "away.json"), "--out", str(png)]
    )
    assert code == 0
    warn_lines = [ln for ln in err.splitlines() if ln.startswith("dvr-perception: warning: ")]
    assert warn_lines, err
    assert "Traceback" not in err
    image = read_png(png)
    assert image.shape == (32, 32, 3)
    assert image.max() == 0


def test_demo_writes_outputs(capsys, tmp_path):
    out_dir = tmp_path / "demo"
    code, out, err = _run(capsys, ["demo", "--out", str(out_dir), "--size", "32"])
    assert code == 0, err
    names = {p.name for p in out_dir.iterdir()}
    render = {"phantom.png", "phantom_buffers.npz", "phantom_spec.json", "visible_share.png"}
    optimized = {"before_after.png", "convergence.png", "optimized_spec.json", "result.json"}
    assert render | optimized <= names
    assert read_png(out_dir / "phantom.png").shape == (32, 32, 3)
    assert "before -> after" in out
    grid = read_png(out_dir / "visible_share.png")
    assert min(grid.shape[:2]) > 100
    spec = json.loads((out_dir / "phantom_spec.json").read_text())
    assert len(spec["structures"]) >= 1
    assert "accumulated coverage" in out
    for s in spec["structures"]:
        assert s["name"] in out


@pytest.mark.vtk_render
def test_check_renderer_phantom_matches_vtk(capsys, tmp_path, vtk_can_render):
    code, out, err = _run(
        capsys,
        ["check-renderer", "phantom", "--size", "96", "--out-dir", str(tmp_path), "--json"],
    )
    assert code == 0, err
    report = _one_json(out)
    for key in ("ssim", "mean_abs_diff", "ours_png", "vtk_png", "mapper", "size"):
        assert key in report
    assert report["mapper"] == "fixed_point"
    assert report["size"] == [96, 96]
    assert report["ssim"] > 0.9
    assert read_png(report["vtk_png"]).shape == (96, 96, 3)
    assert read_png(report["ours_png"]).shape == (96, 96, 3)
    assert min(report["seconds_ours"], report["seconds_vtk"]) > 0


@pytest.mark.vtk_render
def test_bench_reports_keys(capsys, vtk_can_render):
    code, out, err = _run(capsys, ["bench", "--size", "24", "--repeat", "1", "--json"])
    assert code == 0, err
    report = _one_json(out)
    for key in (
        "frame_s",
        "vtk_frame_s",
        "frame_ratio",
        "render_s",
        "render_ratio",
        "samples_per_s",
        "reeval_s",
        "reeval_vtk_frames",
        "cache_mb",
        "volume",
        "size",
        "backend",
        "numba_threads",
        "curvature_s",
        "load_s",
    ):
        assert key in report, key
    assert report["volume"] == "phantom"
    assert report["size"] == [24, 24]
    assert min(report["frame_s"], report["vtk_frame_s"]) > 0
    assert report["frame_ratio"] == pytest.approx(report["frame_s"] / report["vtk_frame_s"])
    # the full analysis (no cache, the skipping walk) and the cache-building one, both timed
    ratio = report["frame_cache_s"] / report["vtk_frame_s"]
    assert report["frame_cache_ratio"] == pytest.approx(ratio)
    assert report["samples_walked"] <= report["samples_walked_cache"] <= report["samples"]
    assert report["render_ratio"] == pytest.approx(report["render_s"] / report["vtk_frame_s"])
    assert report["cache_mb"] > 0
    # the phantom's skin encloses the skull: measure walks its pixels without it (D7)
    assert report["recomposite_layers"] >= 1
    assert report["recomposite_rays"] > 0
    assert 0 < report["recomposite_s"] < report["measure_total_s"]
    assert report["recomposite_vtk_frames"] == pytest.approx(
        report["recomposite_s"] / report["vtk_frame_s"]
    )
    # VTK rendered in a child process: its memory is reported apart from the engine's
    assert report["vtk_peak_rss_mb"] > 30
    assert report["peak_rss_vtk_ratio"] == pytest.approx(
        report["peak_rss_mb"] / report["vtk_peak_rss_mb"]
    )


def test_bench_alternates_frames_and_survives_a_vtk_that_cannot_render(capsys, monkeypatch):
    """Our frames and VTK's are timed in turn; when VTK fails, ours are still reported."""
    import contextlib

    from dvr_perception.errors import DVRInputError
    from dvr_perception.rays import engine, vtk_process, vtk_reference

    order = []
    real_analyze = engine.analyze

    def analyze(*args, **kwargs):
        if kwargs.get("rays") is not None:
            pass  # the measures' re-walk of an encloser's pixels (D7), inside "frame"'s turn
        elif not kwargs.get("occlusion_free", True):
            order.append("render")
        else:
            order.append("cache" if kwargs.get("build_cache", False) else "frame")
        return real_analyze(*args, **kwargs)

    @contextlib.contextmanager
    def timer(*_):
        def frame():
            order.append("vtk")
            if order.count("vtk") == 3:
                raise DVRInputError("VTK: no OpenGL here")
            return 0.5

        yield frame

    monkeypatch.setattr(engine, "analyze", analyze)
    monkeypatch.setattr(vtk_reference, "vtk_frame_timer", timer)
    monkeypatch.setattr(vtk_process, "vtk_frame_process", timer)
    code, out, err = _run(capsys, ["bench", "--size", "16", "--repeat", "4", "--json"])
    assert code == 0, err
    report = _one_json(out)
    # warm-ups, two turns, VTK fails on the third, our two missing turns are timed alone;
    # a turn: the full analysis, the one building the cache, the image, the measure's
    turn = ["frame", "cache", "render", "frame"]
    warm = ["frame", "render", "cache"]
    assert order[:22] == [*warm, "vtk", *turn, "vtk", *turn, "vtk", *turn, *turn]
    assert report["vtk_frame_s"] is None
    assert report["frame_ratio"] is None
    assert report["render_ratio"] is None
    assert report["measure_vtk_frames"] is None
    assert report["vtk_error"] == "VTK: no OpenGL here"
    assert report["frame_s"] > 0
    assert report["render_s"] > 0
    # two medians timed apart: at 16 px their order is noise, so only their presence is checked
    assert report["measure_total_s"] > 0
    assert report["measure_s"] > 0
    # the walk behind early ray termination: the cache's and the exact one visit the same
    # samples, the full analysis (no cache) skips (D8) and visits at most as many
    assert report["samples_walked_exact"] == report["samples_walked_cache"]
    assert report["samples_walked"] == report["samples_walked_skipping"]
    assert 0 < report["samples_walked_skipping"] <= report["samples_walked_exact"]


def test_bench_rejects_bad_repeat(capsys):
    code, _, err = _run(capsys, ["bench", "--repeat", "0"])
    assert code == 2
    assert err.strip() == "dvr-perception: error: --repeat: expected a positive integer, got 0"
