"""Bad input to the CLI: exit 2, one ``dvr-perception: error:`` line, no traceback, no files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dvr_perception.cli import main
from dvr_perception.cli._common import parse_size
from dvr_perception.errors import DVRInputError

GOOD_STRUCTURE = {"name": "a", "range": [10, 200], "importance": 0.5, "color": [1, 1, 1]}


def _run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _assert_one_error(err: str, *needles: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dvr-perception: error: ")
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0]


def _bad_case(kind: str, tmp: Path) -> tuple[list[str], str]:
    """Return (extra argv, expected text in the message) for one kind of bad input."""
    if kind == "missing_file":
        return [str(tmp / "nope.nhdr")], "nope.nhdr"
    if kind == "truncated_raw":
        (tmp / "trunc.raw").write_bytes(bytes(100))
        (tmp / "trunc.nhdr").write_text(
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n"
            "endian: little\ndata file: trunc.raw\n"
        )
        return [str(tmp / "trunc.nhdr")], "trunc"
    if kind == "malformed_spec":
        (tmp / "bad.json").write_text('{"version": 1, "structures": [')
        return ["phantom", "--structures", str(tmp / "bad.json")], "bad.json"
    if kind == "spec_out_of_range":
        spec = {"version": 1, "structures": [{**GOOD_STRUCTURE, "importance": 1.5}]}
        (tmp / "range.json").write_text(json.dumps(spec))
        return ["phantom", "--structures", str(tmp / "range.json")], "importance"
    if kind == "view_four_numbers":
        return ["phantom", "--view", "1,2,3,4"], "--view"
    if kind == "size_zero":
        return ["phantom", "--size", "0"], "--size"
    if kind == "camera_unknown_field":
        (tmp / "cam.json").write_text(json.dumps({"position": [0, 0, 5], "fov": 30}))
        return ["phantom", "--camera", str(tmp / "cam.json")], "fov"
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind",
    [
        "missing_file",
        "truncated_raw",
        "malformed_spec",
        "spec_out_of_range",
        "view_four_numbers",
        "size_zero",
        "camera_unknown_field",
    ],
)
def test_bad_input_exit_2_one_line(capsys, tmp_path, kind):
    argv, needle = _bad_case(kind, tmp_path)
    out_png = tmp_path / "out.png"
    code, out, err = _run(capsys, ["render", *argv, "--out", str(out_png), "--json"])
    assert code == 2
    _assert_one_error(err, needle)
    assert out == ""
    assert not out_png.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_view_and_camera_are_exclusive(capsys, tmp_path):
    code, _, err = _run(
        capsys,
        ["render", "phantom", "--view", "0,0", "--camera", "c.json", "--out", "x.png"],
    )
    assert code == 2
    _assert_one_error(err, "--camera", "--view")


@pytest.mark.parametrize("command", ["render", "app"])
def test_bad_orientation_code_is_the_same_error_for_the_app(capsys, command):
    """``app --orientation`` is checked as the other commands' (before any server starts)."""
    argv = [command, "phantom", "--orientation", "LPQ"]
    code, _, err = _run(capsys, [*argv, "--out", "x.png"] if command == "render" else argv)
    assert code == 2
    _assert_one_error(err, "--orientation: expected three letters from L/R, P/A, S/I", "'LPQ'")


def test_missing_output_directory_fails_before_rendering(capsys, tmp_path):
    code, _, err = _run(capsys, ["render", "phantom", "--out", str(tmp_path / "no" / "x.png")])
    assert code == 2
    _assert_one_error(err, "does not exist")


def test_unknown_command(capsys):
    code, _, err = _run(capsys, ["paint"])
    assert code == 2
    _assert_one_error(err, "paint")


def test_help_exits_zero(capsys):
    code, out, _ = _run(capsys, ["render", "--help"])
    assert code == 0
    assert "--buffers" in out


def test_unexpected_error_is_exit_1_and_one_line(capsys, monkeypatch):
    import dvr_perception.cli.render as render_cmd

    def boom(args):
        raise ZeroDivisionError("oops")

    monkeypatch.setattr(render_cmd, "run", boom)
    code, _, err = _run(capsys, ["render", "phantom", "--out", "x.png"])
    assert code == 1
    _assert_one_error(err, "ZeroDivisionError", "oops", "--debug")
    code, _, err = _run(capsys, ["render", "phantom", "--out", "x.png", "--debug"])
    assert code == 1
    assert "Traceback" in err
    assert err.strip().splitlines()[-1].startswith("dvr-perception: error: unexpected")


@pytest.mark.parametrize(
    ("text", "expected"), [("64", (64, 64)), ("320x200", (320, 200)), (" 8X9 ", (8, 9))]
)
def test_parse_size(text, expected):
    assert parse_size(text) == expected


@pytest.mark.parametrize("text", ["0", "-3", "12x", "x12", "1.5", "20000", "4x0"])
def test_parse_size_rejects(text):
    with pytest.raises(DVRInputError, match="--size"):
        parse_size(text)


def test_console_script_error_path(tmp_path):
    script = Path(sys.executable).parent / "dvr-perception"
    assert script.is_file(), f"console script not installed next to {sys.executable}"
    proc = subprocess.run(
        [str(script), "render", str(tmp_path / "missing.nhdr"), "--out", str(tmp_path / "x.png")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    _assert_one_error(proc.stderr, "missing.nhdr")
