"""``optimize``'s one-time costs (issue 31): the result first, the figures after, lean imports.

The result (images, spec, presets, ``result.json``) is in the output folder and printed before
a single figure is drawn; ``--no-figures`` skips them; a failure or an interrupt while they
are drawn leaves the complete result (and no partial figure); a rerun never mixes its result
with an earlier run's figures.  Importing the command line pulls in neither matplotlib, scipy,
scikit-image, numba nor VTK, and the result is written without matplotlib.  PNG files are
encoded without VTK (:func:`dvr_perception._files.png_bytes`) and read back exactly by VTK.
"""

from __future__ import annotations

import json
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from dvr_perception._files import LOCK_NAME, Terminated, png_bytes, read_png, write_png
from dvr_perception.cli import main
from dvr_perception.cli import optimize as optimize_cmd
from dvr_perception.structures.io import save_spec
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.volume import save_volume

#: The files of step 1 (the result).
RESULT = {
    "before.png",
    "after.png",
    "optimized_spec.json",
    "paraview_preset.json",
    "slicer.vp.json",
    "result.json",
}
ARGS = ["--size", "24", "--stages", "opacity", "--max-iter", "2"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 24^3 phantom volume and its spec, as files (faster than the built-in 128^3)."""
    d = tmp_path_factory.mktemp("scene")
    vol, spec = make_phantom(size=24)
    save_volume(vol, d / "ph.nhdr")
    save_spec(spec, d / "ph.json")
    return [str(d / "ph.nhdr"), "--structures", str(d / "ph.json")]


def _names(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


def _optimize(capsys, scene, out: Path, *extra):
    code = main(["optimize", *scene, *ARGS, "--out", str(out), *extra])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_figures_are_drawn_after_the_result_is_written_and_printed(
    capsys, scene, tmp_path, monkeypatch
):
    out = tmp_path / "o"
    seen = {}
    real = optimize_cmd.write_figures

    def spy(staging, drawing):
        seen["folder"] = _names(out)  # what the folder holds when the first figure is drawn
        seen["printed"] = capsys.readouterr().out
        seen["result"] = json.loads((out / "result.json").read_text())
        return real(staging, drawing)

    monkeypatch.setattr(optimize_cmd, "write_figures", spy)
    code, stdout, err = _optimize(capsys, scene, out)
    assert code == 0, err
    assert {n for n in seen["folder"] if not n.startswith(".")} == RESULT  # not one figure yet
    assert LOCK_NAME in seen["folder"]  # the folder stays locked while the figures are drawn
    assert "optimised" in seen["printed"]
    assert "the figures follow" in seen["printed"]
    assert seen["result"]["figures"] == []
    assert sorted(Path(f).name for f in seen["result"]["files"]) == sorted(RESULT)
    # then the figures, and result.json rewritten to list them
    assert _names(out) == RESULT | set(optimize_cmd.FIGURES)
    assert f"figures: wrote {len(optimize_cmd.FIGURES)} more files" in stdout
    report = json.loads((out / "result.json").read_text())
    assert [Path(f).name for f in report["figures"]] == list(optimize_cmd.FIGURES)
    assert sorted(Path(f).name for f in report["files"]) == sorted(_names(out))
    assert set(report["timings"]) == {"startup", "load", "optimise", "measure", "write",
                                      "figures"}  # fmt: skip
    assert all(v is None or v >= 0 for v in report["timings"].values())


def test_no_figures_writes_the_result_only_and_json_lists_it(capsys, scene, tmp_path):
    out = tmp_path / "o"
    code, stdout, err = _optimize(capsys, scene, out, "--no-figures", "--json")
    assert code == 0, err
    report = json.loads(stdout)
    assert _names(out) == RESULT
    assert report["figures"] == []
    assert sorted(report["files"]) == sorted(str(out / f) for f in RESULT)
    assert "figures" not in report["timings"]
    assert json.loads((out / "result.json").read_text())["final"] == report["final"]


def test_json_with_figures_is_the_final_result_json(capsys, scene, tmp_path):
    out = tmp_path / "o"
    code, stdout, err = _optimize(capsys, scene, out, "--json")
    assert code == 0, err
    report = json.loads(stdout)
    assert report == json.loads((out / "result.json").read_text())
    assert len(report["figures"]) == len(optimize_cmd.FIGURES)
    assert read_png(out / "before_after.png").shape[2] in (3, 4)


def test_a_rerun_without_figures_removes_the_earlier_runs_figures(capsys, scene, tmp_path):
    out = tmp_path / "o"
    assert _optimize(capsys, scene, out)[0] == 0
    (out / "mine.txt").write_text("kept")
    assert _names(out) == RESULT | set(optimize_cmd.FIGURES) | {"mine.txt"}
    assert _optimize(capsys, scene, out, "--no-figures")[0] == 0
    assert _names(out) == RESULT | {"mine.txt"}  # no stale figure beside the new result
    assert (out / "mine.txt").read_text() == "kept"


@pytest.mark.parametrize(
    ("error", "code"),
    [(RuntimeError("drawing failed"), 1), (KeyboardInterrupt(), 130), (Terminated(), 143)],
    ids=["error", "ctrl-c", "sigterm"],
)
def test_a_failure_while_drawing_keeps_the_whole_result_and_no_figure(
    capsys, scene, tmp_path, monkeypatch, error, code
):
    out = tmp_path / "o"

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(optimize_cmd._plots, "save_convergence", fail)  # the last: others staged
    got, stdout, err = _optimize(capsys, scene, out)
    assert got == code, err
    assert _names(out) == RESULT  # no figure, no staging folder, no lock
    report = json.loads((out / "result.json").read_text())
    assert report["figures"] == []
    assert sorted(Path(f).name for f in report["files"]) == sorted(RESULT)
    assert "optimised" in stdout  # the result was printed before the failure


def _modules_after(code: str) -> set[str]:
    """Top-level packages imported by ``code`` in a fresh interpreter."""
    probe = (
        f"{code}\nimport sys, json\n"
        "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))"
    )
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          check=False, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return set(json.loads(proc.stdout.strip().splitlines()[-1]))


HEAVY = {"matplotlib", "scipy", "skimage", "numba", "vtkmodules", "PIL"}


def test_importing_the_command_line_imports_no_heavy_package():
    assert _modules_after("import dvr_perception.cli") & HEAVY == set()


def test_the_result_is_written_without_matplotlib(scene, tmp_path):
    out = tmp_path / "o"
    argv = ["optimize", *scene, *ARGS, "--out", str(out), "--no-figures"]
    loaded = _modules_after(f"from dvr_perception.cli import main\nassert main({argv!r}) == 0")
    assert "matplotlib" not in loaded
    assert "PIL" not in loaded
    assert _names(out) == RESULT


@pytest.mark.parametrize("channels", [3, 4])
def test_png_encoder_round_trips_through_vtks_reader(tmp_path, channels):
    rng = np.random.default_rng(channels)
    pixels = rng.integers(0, 256, (5, 7, channels), dtype=np.uint8)
    path = write_png(tmp_path / "x.png", pixels)
    assert np.array_equal(read_png(path), pixels)  # row 0 at the top, every channel


def test_png_encoder_writes_the_plain_format():
    blob = png_bytes(np.array([[[255, 0, 0], [0, 0, 255]]], np.uint8))  # 1 x 2 RGB
    assert blob[:8] == b"\x89PNG\r\n\x1a\n"
    assert blob[8:16] == b"\x00\x00\x00\x0dIHDR"
    assert blob[16:29] == bytes([0, 0, 0, 2, 0, 0, 0, 1, 8, 2, 0, 0, 0])  # 2 x 1, 8-bit RGB
    n = int.from_bytes(blob[33:37], "big")
    assert blob[37:41] == b"IDAT"
    assert zlib.decompress(blob[41 : 41 + n]) == bytes([0, 255, 0, 0, 0, 0, 255])
    assert blob[-12:] == b"\x00\x00\x00\x00IEND\xaeB`\x82"
