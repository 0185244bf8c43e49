"""Hostile structure names: length and printable characters (issue 29).

A spec JSON's names are refused when longer than ``MAX_NAME_LENGTH`` or holding a character
that is not printable (one error naming the file, the structure and the field); a Slicer
segmentation's names are sanitised with a warning; no output lets a control character reach
the terminal, and no figure depends on a name's length or on ``$`` (matplotlib's mathtext).
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dvr_perception.cli import _plots
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures.io import spec_from_dict
from dvr_perception.structures.slicer import spec_from_segmentation, write_segmentation
from dvr_perception.structures.spec import MAX_NAME_LENGTH, Structure, name_problem, printable

#: Characters a terminal acts on (ESC, BEL, CR, DEL, a C1 control, the right-to-left override,
#: a zero-width joiner, the line separator) and a tab and newline.
HOSTILE = ["\x1b[2J", "\x07", "\r", "\x7f", "\x9b", "\u202e", "\u200d", "\u2028", "\t", "\n"]


def _spec(name) -> dict:
    return {"version": 1, "structures": [
        {"name": "ok", "range": [0, 10], "importance": 0.5, "color": [1, 1, 1]},
        {"name": name, "range": [10, 200], "importance": 0.5, "color": [1, 0, 0]}]}  # fmt: skip


def _raw_control(text: str) -> list[str]:
    """Characters of ``text`` a terminal would act on (all but the line ends between lines)."""
    return [ch for line in text.splitlines() for ch in line if not ch.isprintable()]


# -- the spec ----------------------------------------------------------------------------------


def test_a_name_of_the_longest_length_is_accepted_one_more_is_refused():
    name = "n" * MAX_NAME_LENGTH
    assert spec_from_dict(_spec(name), source="s.json").structures[1].name == name
    with pytest.raises(DVRInputError) as err:
        spec_from_dict(_spec(name + "n"), source="s.json")
    assert str(err.value) == (
        f"s.json: structures[1].name must be at most {MAX_NAME_LENGTH} characters, got "
        f"{MAX_NAME_LENGTH + 1} characters"
    )


@pytest.mark.parametrize("bad", HOSTILE, ids=[ascii(c) for c in HOSTILE])
def test_a_name_with_a_non_printable_character_is_refused(bad):
    with pytest.raises(DVRInputError) as err:
        spec_from_dict(_spec(f"bone{bad}x"), source="s.json")
    message = str(err.value)
    assert message.startswith("s.json: structures[1].name must hold printable characters only")
    assert f"got {bad[0]!a} at position 4" in message
    assert _raw_control(message) == []


def test_unicode_names_that_print_are_accepted():
    for name in ("Knochen äöü", "骨", "tumour (T1, 5 mm)", "a $b$ c", "x" * 10):
        assert name_problem(name) is None
        assert spec_from_dict(_spec(name)).structures[1].name == name


def test_a_structure_made_in_code_is_checked_too():
    with pytest.raises(DVRInputError, match="printable"):
        Structure("a\x1b[31m", 0.5, (1, 1, 1), range=(0, 1))
    with pytest.raises(DVRInputError, match=f"at most {MAX_NAME_LENGTH}"):
        Structure("a" * 10**6, 0.5, (1, 1, 1), range=(0, 1))
    with pytest.raises(DVRInputError, match="non-empty string"):
        Structure(3, 0.5, (1, 1, 1), range=(0, 1))  # type: ignore[arg-type]


def test_printable_escapes_and_cuts():
    assert printable("a\x1b[2Jb\u202ec") == "a\\x1b[2Jb\\u202ec"
    assert printable("é骨") == "é骨"
    assert printable("x" * 100, 10) == "x" * 9 + "…"
    assert printable("\x00" * 10**6, 12) == "\\x00\\x00\\x0…"
    assert printable("x" * 10**7, 40) == "x" * 39 + "…"


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(name=st.text(max_size=200), limit=st.integers(1, 80))
def test_any_name_is_refused_or_printable_and_printable_always_prints(name, limit):
    try:
        spec = spec_from_dict(_spec(name), source="s.json")
    except DVRInputError as exc:
        message = str(exc)
        spec = None
    if spec is None:
        assert message.startswith("s.json: structures[1].name"), message
        assert _raw_control(message) == []
    else:
        got = spec.structures[1].name
        assert got == name
        assert got.isprintable()
        assert len(got) <= MAX_NAME_LENGTH
    shown = printable(name, limit)
    assert shown.isprintable()
    assert len(shown) <= limit
    if name.isprintable() and len(name) <= limit:
        assert shown == name


# -- Slicer segmentations: sanitised -----------------------------------------------------------


def _segmentation(path: Path, names) -> Path:
    labels = np.zeros((4, 4, 4), np.uint8)
    segments = []
    for i, name in enumerate(names, start=1):
        labels[i - 1] = i
        segments.append({"name": name, "color": (1.0, 0.5, 0.0), "label": i})
    return write_segmentation(path, labels, segments)


def test_slicer_names_are_sanitised_with_a_warning(tmp_path):
    long = "left internal carotid artery " * 20  # 580 characters
    path = _segmentation(tmp_path / "s.seg.nrrd", ["ok", "bad\x1b[2Jname\x7f", long])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        spec = spec_from_segmentation(path)
    names = spec.names
    assert names[0] == "ok"
    assert names[1] == "bad\\x1b[2Jname\\x7f"
    assert names[2] == long[: MAX_NAME_LENGTH - 1] + "…"
    assert all(name_problem(n) is None for n in names)
    messages = [str(w.message) for w in caught if issubclass(w.category, DVRWarning)]
    assert len(messages) == 2, messages
    assert "Segment1_Name must hold printable characters only" in messages[0]
    assert str(path) in messages[0]
    assert f"Segment2_Name must be at most {MAX_NAME_LENGTH} characters" in messages[1]
    assert all(_raw_control(m) == [] for m in messages)


def test_slicer_names_that_become_equal_are_refused(tmp_path):
    a, b = "x" * 100 + "a", "x" * 100 + "b"  # the same once cut
    path = _segmentation(tmp_path / "d.seg.nrrd", [a, b])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DVRWarning)
        with pytest.raises(DVRInputError, match=r"Segment1_Name.*duplicates Segment0_Name"):
            spec_from_segmentation(path)


# -- figures -----------------------------------------------------------------------------------


def _per_structure(names, bins: int = 4) -> dict:
    return {n: {"histogram_visible": np.arange(bins), "histogram_assigned": np.ones(bins),
                "visible_share": 0.5, "target_share": 0.5, "rays": 10} for n in names}  # fmt: skip


def test_figures_draw_names_with_dollars_literally(tmp_path):
    """``$\\notacommand$`` would be mathtext and fail the whole figure."""
    names = [r"a $\notacommand$ b", "$x^$", "c\\$d$"]
    assert _plots.plot_text(names[0]) == r"a \$\notacommand\$ b"
    out = _plots.save_visibility_histograms(
        tmp_path / "h.png", _per_structure(names), np.linspace(0, 1, 5), title="t"
    )
    assert out.stat().st_size > 0
    regions = [{"id": 0, "layers": names[:2], "kind": "x", "area_fraction": 1.0}]
    out = _plots.save_region_map(tmp_path / "r.png", np.zeros((8, 8), int), regions, title="r")
    assert out.stat().st_size > 0


def test_region_legend_is_bounded(tmp_path):
    """Hundreds of layer sets of 32 longest names: a bounded legend, drawn in seconds."""
    names = [f"{i:02d}" + "n" * (MAX_NAME_LENGTH - 2) for i in range(32)]
    n = 300
    regions = [{"id": i, "layers": [names[i % 32], names[(i * 7) % 32], names[i // 32]],
                "kind": "x", "area_fraction": 1.0 / n} for i in range(n)]  # fmt: skip
    rid = np.arange(n).reshape(15, 20)
    t0 = time.perf_counter()
    _plots.save_region_map(tmp_path / "r.png", rid, regions, title="many")
    assert time.perf_counter() - t0 < 20.0


# -- the command line --------------------------------------------------------------------------


def _cli_cases(root: Path) -> dict:
    """Build the command-line cases: ``name -> {"argv", "cwd"[, "alone"], "out"}``."""
    from dvr_perception.volume import Volume, save_volume

    cases = {}
    for command in ("measure", "optimize"):
        run = root / f"long-{command}"
        run.mkdir()
        (run / "long.json").write_text(json.dumps(_spec("n" * 10**6)))
        flag = "--out-dir" if command == "measure" else "--out"
        argv = [command, "phantom", "--structures", "long.json", "--size", "16", flag, "out"]
        cases[f"long-{command}"] = {"argv": argv, "cwd": str(run)}
    run = root / "esc"
    run.mkdir()
    (run / "esc.json").write_text(json.dumps(_spec("bone\x1b]0;owned\x07\x1b[2J")))
    cases["esc"] = {"argv": ["measure", "phantom", "--structures", "esc.json", "--size", "16"],
                    "cwd": str(run)}  # fmt: skip
    run = root / "path"
    run.mkdir()
    cases["path"] = {"argv": ["measure", "vol\x1b[2J\x07.nhdr", "--size", "16"], "cwd": str(run)}
    cases["path-verbose"] = {"argv": [*cases["path"]["argv"], "-v"], "cwd": str(run)}
    run = root / "slicer"
    run.mkdir()
    labels = np.zeros((12, 12, 12), np.uint8)
    labels[3:9, 3:9, 3:9] = 1
    labels[5:7, 5:7, 5:7] = 2
    save_volume(Volume(labels * 100), run / "v.nhdr")
    segs = [{"name": "shell\x1b[2J", "color": (1, 1, 1), "label": 1},
            {"name": "core\u202e\u202e", "color": (1, 0, 0), "label": 2}]  # fmt: skip
    write_segmentation(run / "s.seg.nrrd", labels, segs)
    cases["slicer"] = {"argv": ["measure", "v.nhdr", "--structures", "s.seg.nrrd", "--size",
                                "16", "--save-spec", "saved.json", "--out-dir", "out"],
                       "cwd": str(run), "alone": True}  # fmt: skip
    return cases


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory, batch):
    root = tmp_path_factory.mktemp("names")
    cases = _cli_cases(root)
    results = batch(list(cases.values()), root)
    return {name: (Path(case["cwd"]), r) for (name, case), r in zip(cases.items(), results,
                                                                    strict=True)}  # fmt: skip


@pytest.mark.parametrize("command", ["measure", "optimize"])
def test_a_million_character_name_is_refused_at_once(cli_runs, command):
    """The case of issue 29 (60 s and 0.9 GB in the plots): one error within bounds, no file."""
    run, result = cli_runs[f"long-{command}"]
    line = result.one_error("long.json", "structures[1].name", f"at most {MAX_NAME_LENGTH}")
    assert "n" * 100 not in line
    assert sorted(p.name for p in run.iterdir()) == ["long.json"]


def test_control_characters_in_a_name_never_reach_the_terminal(cli_runs):
    _, result = cli_runs["esc"]
    line = result.one_error("esc.json", "structures[1].name", "printable", "'\\x1b'")
    assert _raw_control(result.stderr) == []
    assert "\x1b" not in line


def test_control_characters_in_a_path_are_escaped_in_errors(cli_runs):
    _, result = cli_runs["path"]
    result.one_error("vol\\x1b[2J\\x07.nhdr")
    assert _raw_control(result.stderr + result.stdout) == []


def test_control_characters_in_a_path_are_escaped_in_the_log(cli_runs):
    _, result = cli_runs["path-verbose"]
    assert result.code == 2
    assert "dvr-perception: loading volume vol\\x1b[2J\\x07.nhdr" in result.stderr
    assert _raw_control(result.stderr + result.stdout) == []


def test_sanitised_slicer_names_reach_every_output_escaped(cli_runs):
    """A segmentation's ESC and RLO names: warnings, summary, JSON, spec: printable only."""
    run, result = cli_runs["slicer"]
    assert result.code == 0, result.stderr
    result.bounded()
    assert _raw_control(result.stderr + result.stdout) == []
    assert "shell\\x1b[2J" in result.stdout
    warns = [line for line in result.stderr.splitlines() if "warning" in line]
    assert len([w for w in warns if "_Name" in w]) == 2, result.stderr
    expected = ["shell\\x1b[2J", "core\\u202e\\u202e"]
    saved = json.loads((run / "saved.json").read_text(encoding="utf-8"))
    assert [s["name"] for s in saved["structures"]] == expected
    report = json.loads((run / "out" / "measures.json").read_text(encoding="utf-8"))
    assert list(report["structures"]) == expected
    for path in (run / "out").iterdir():
        if path.suffix == ".json":
            assert _raw_control(path.read_text(encoding="utf-8")) == []
