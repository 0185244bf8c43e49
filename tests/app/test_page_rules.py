"""The rules of :mod:`dvr_perception.app.page_input` and :func:`.security.message_problem`.

No server: each rule gets a small app stand-in (a 10 mm cube, three structures, values 0 to
100); ``tests/app/test_page_input.py`` drives the same rules over the real protocol.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from dvr_perception.app.page_input import (
    STATE,
    TRIGGERS,
    Camera,
    PageInputGuard,
    Refused,
    Upload,
)
from dvr_perception.app.security import message_problem

CTX = SimpleNamespace(
    session=SimpleNamespace(
        spec=SimpleNamespace(structures=("a", "b", "c")),
        volume=SimpleNamespace(bounds=(0.0, 10.0, 0.0, 10.0, 0.0, 10.0)),
    ),
    max_upload_bytes=1000,
    _histogram=lambda: {"lo": 0.0, "hi": 100.0},
)
UP = [0.0, 1.0, 0.0]


def _camera(position, focal=(5.0, 5.0, 5.0), up=UP):
    return {"position": list(position), "focalPoint": list(focal), "viewUp": list(up)}


def test_a_camera_near_the_volume_is_taken_and_extra_keys_dropped():
    cam = {**_camera((5.0, 5.0, 40.0)), "viewAngle": 30, "parallelProjection": False}
    assert Camera("camera").check(cam, CTX) == _camera((5.0, 5.0, 40.0))


@pytest.mark.parametrize(
    ("cam", "says"),
    [
        (_camera((1e308, 0.0, 0.0)), "position within 1.73e+04"),  # 1000 diagonals of 17.3 mm
        (_camera((5.0, 5.0, 5.0 + 17321.0)), "position within"),
        (_camera((5.0, 5.0, 40.0), focal=(5.0, 5.0, 1e9)), "focalPoint within"),
        (_camera((math.nan, 0.0, 0.0)), "camera.position nan"),
        (_camera((math.inf, 0.0, 0.0)), "camera.position inf"),
        (_camera((5.0, 5.0, 5.0)), "apart from the focal point"),
        (_camera((5.0, 5.0, 40.0), up=(0.0, 0.0, 0.0)), "viewUp not zero"),
        (_camera((5.0, 5.0, 40.0), up=(0.0, 0.0, 2.0)), "not along the view direction"),
        ({"position": [1, 2], "focalPoint": [0, 0, 0], "viewUp": UP}, "position: three"),
        ({"position": "1,2,3", "focalPoint": [0, 0, 0], "viewUp": UP}, "position: three"),
        ([1, 2, 3], "a camera {position"),
    ],
)
def test_an_absurd_camera_is_refused(cam, says):
    with pytest.raises(Refused, match=r"^camera") as info:
        Camera("camera").check(cam, CTX)
    assert says in str(info.value)


def test_just_inside_the_camera_bound_is_taken():
    diag = math.sqrt(300.0)
    Camera("camera").check(_camera((5.0, 5.0, 5.0 + 999.0 * diag)), CTX)


def test_an_upload_in_parts_is_joined_and_its_size_bounded():
    up = Upload("upload")
    got = up.check([{"name": "a.nrrd", "size": 6, "content": [b"abc", b"def"], "type": ""}], CTX)
    assert got == {"name": "a.nrrd", "size": 6, "content": b"abcdef"}
    with pytest.raises(Refused, match="upload content as bytes"):
        up.check({"name": "a.nrrd", "size": 3, "content": [1, 2, 3]}, CTX)
    with pytest.raises(Refused, match="at most 1000 bytes"):
        up.check({"name": "a.nrrd", "size": 3, "content": [b"x" * 600, b"y" * 600]}, CTX)
    with pytest.raises(Refused, match="size -1: expected an integer from 0 to 1000"):
        up.check({"name": "a.nrrd", "size": -1, "content": b""}, CTX)
    with pytest.raises(Refused, match=r"upload\.name"):
        up.check({"name": None, "size": 0, "content": b""}, CTX)


@pytest.mark.parametrize(
    ("name", "value", "says"),
    [
        ("map_kind", "../../etc", "map kind '../../etc': expected one of visibility"),
        ("map_opacity", True, "map strength True: expected a number"),
        ("map_opacity", 1e308, "map strength 1e+308: expected a number from 0 to 1"),
        ("rank_structure", 3, "ranking structure 3: expected an integer from 0 to 2"),
        ("rank_structure", 1.5, "ranking structure 1.5"),
        ("rank_order", ["img1", "img1"], "expected distinct items"),
        ("rank_order", [1], "ranking order item 1: expected the id of a ranking image"),
        ("orientation_code", "lps", "orientation 'lps': expected one of , LPS"),
        ("spec_name", "a\x00b", "without control characters"),
        ("tf_edit", {"index": 0, "kind": "mid", "fx": 0, "fy": 0}, "kind 'mid'"),
        ("tf_edit", {"index": 0, "kind": "lo", "fx": 0}, "keys index, kind, fx, fy"),
        ("lens", {"shape": "circle", "x0": 0.5, "y0": 0.5}, "keys shape, x0, y0, r"),
        ("lens", {"shape": "star", "x0": 0.5, "y0": 0.5, "x1": 1, "y1": 1}, "shape 'star'"),
    ],
)
def test_state_rules_name_the_variable_and_what_was_expected(name, value, says):
    with pytest.raises(Refused) as info:
        STATE[name].check(value, CTX)
    assert says in str(info.value)


def test_state_rules_take_what_the_page_sends():
    assert STATE["tf_edit"].check(None, CTX) is None
    edit = {"index": 2, "kind": "hi", "fx": 1.2, "fy": -0.1}
    assert STATE["tf_edit"].check(edit, CTX) == edit
    assert STATE["rank_structure"].check(2.0, CTX) == 2
    assert STATE["orientation_code"].check("", CTX) == ""
    lens = {"shape": "circle", "x0": 0.5, "y0": 0.5, "r": 0.2, "w": 300, "h": 200}
    assert STATE["lens"].check(lens, CTX) == lens


@pytest.mark.parametrize(
    ("action", "args", "says"),
    [
        ("set_range", [0, 0, "50.5"], None),
        ("set_range", [0, 0, "-100"], None),  # the span below the values
        ("set_range", [0, 0, "-100.5"], "range value '-100.5': expected a number from -100"),
        ("set_range", [0, 2, "5"], "range end 2: expected one of 0, 1"),
        ("set_range", [0, 0.0, "5"], "range end 0.0"),  # 0.0 is no index
        ("set_colour", [1, "#00ff7F"], None),
        ("set_colour", [1, "red"], "colour 'red': expected a colour #rrggbb"),
        ("set_lens_target", [0, "use_tr", True], None),
        ("set_lens_target", [0, "use_tr", 1], "lens target use_tr 1: expected true or false"),
        ("set_lens_target", [0, "__class__", 1], "lens target field '__class__'"),
        ("optimise", [], None),
        ("optimise", ["all", True], None),
        ("optimise", ["all", "yes"], "optimise in lens 'yes'"),
        ("undo", [51], "undo steps 51: expected an integer from 1 to 50"),
        ("view_axis", ["+X"], None),
        ("cancel", [], None),
        ("cancel", [None], "page action cancel: expected 0 arguments, got 1"),
    ],
)
def test_action_arguments(action, args, says):
    if says is None:
        TRIGGERS[action].check(action, args, {}, CTX)
        return
    with pytest.raises(Refused) as info:
        TRIGGERS[action].check(action, args, {}, CTX)
    assert says in str(info.value)


def test_keyword_arguments_are_refused():
    with pytest.raises(Refused, match="expected 1 argument, got 2"):
        TRIGGERS["view_axis"].check("view_axis", ["+X"], {"evil": 1}, CTX)


def test_state_changes_are_split_into_kept_and_refused():
    guard = PageInputGuard(CTX)
    guard._owned = frozenset({"lens_rows"})
    changes = [
        {"key": "map_kind", "value": "shape"},
        {"key": "map_kind", "value": "../../etc"},
        {"key": "lens_rows", "value": []},
        {"key": "something_new", "value": 1},
        {"value": 3},
        "map_kind",
    ]
    kept, reasons, names = guard.check_changes(changes)
    assert kept == [{"key": "map_kind", "value": "shape"}, {"key": "something_new", "value": 1}]
    assert names == ["map_kind", "lens_rows"]
    assert len(reasons) == 4
    assert "set by the server" in reasons[1]
    assert guard.check_changes(5) == ([], ["state update: expected a list of changes, got 5"], [])


@pytest.mark.parametrize(
    ("rpc", "says"),
    [
        ({"id": "rpc:c1:1", "args": []}, "a message without a method"),
        ({"id": "rpc:c1:1", "method": None}, "a message without a method"),
        ({"id": 5, "method": "m"}, "a message without a text id"),
        ({"method": "m"}, "a message without a text id"),
        ([1, 2], "a message that is no map (list)"),
        ({"id": "x", "method": "m", "args": {"a": 1}}, "m: arguments that are no list"),
        (
            {"id": "x", "method": "m", "kwargs": {1: 2}},
            "m: keyword arguments that are no map of names",
        ),
        ({"id": "x", "method": "f", "args": [1, 2, 3]}, "f: 3 arguments that do not fit it"),
        ({"id": "x", "method": "f", "args": [1]}, None),
        ({"id": "x", "method": "unknown", "args": [1, 2, 3]}, None),  # wslink answers it
    ],
)
def test_malformed_wslink_calls_are_named(rpc, says):
    def f(self, a):
        return a

    assert message_problem(rpc, {"f": (object(), f)}) == says
