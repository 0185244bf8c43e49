"""The transfer-function view's library: histogram, chart geometry, dropped handles, views."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.app.tf_view import (
    BOTTOM,
    HEIGHT,
    LEFT,
    RIGHT,
    TOP,
    WIDTH,
    axis_camera,
    colour_bar_stops,
    dropped_edit,
    tf_chart,
    value_histogram,
)
from dvr_perception.errors import DVRInputError
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.volume import Volume

SPEC = StructureSpec(
    (
        Structure("a", 0.5, (1.0, 0.0, 0.0), range=(10.0, 50.0), edge=0.25),
        Structure("b", 0.4, (0.0, 1.0, 0.0), range=(60.0, 90.0), opacity=0.8),
    )
)
HIST = {"lo": 0.0, "hi": 100.0, "counts": [1, 1000, 0, 10]}


def _fx(value: float) -> float:
    """The chart fraction of a value (0..100 volume)."""
    return (LEFT + (WIDTH - LEFT - RIGHT) * value / 100.0) / WIDTH


def test_histogram_counts_every_voxel_in_its_bin():
    data = np.array([0, 0, 1, 5, 9, 10, 10, 10], np.uint16).reshape(2, 2, 2)
    h = value_histogram(Volume(data), bins=2)
    assert (h["lo"], h["hi"]) == (0.0, 10.0)
    assert h["counts"] == [3, 5]  # [0, 5) and [5, 10]
    with pytest.raises(DVRInputError, match="bins"):
        value_histogram(Volume(data), bins=0)


def test_chart_draws_trapezoids_where_the_spec_puts_them():
    c = tf_chart(HIST, SPEC, before=SPEC.with_opacities([0.1, 0.2]))
    a, b = c["structures"]
    span = WIDTH - LEFT - RIGHT
    base = HEIGHT - BOTTOM
    xs = [float(p.split(",")[0]) for p in a["points"].split()]
    ys = [float(p.split(",")[1]) for p in a["points"].split()]
    assert xs == pytest.approx([LEFT + span * v / 100 for v in (10, 20, 40, 50)], abs=0.06)
    top = TOP + (base - TOP) * (1 - 0.5)  # importance 0.5 is the opacity
    assert ys == pytest.approx([base, top, top, base], abs=0.06)
    assert float(b["y_top"]) == pytest.approx(TOP + (base - TOP) * 0.2, abs=0.06)  # opacity 0.8
    assert (a["color"], b["range"], b["opacity"]) == ("#ff0000", [60.0, 90.0], 0.8)
    # the before curves have the before opacities
    old_top = float(c["before"][1]["points"].split()[1].split(",")[1])
    assert old_top == pytest.approx(TOP + (base - TOP) * 0.8, abs=0.06)
    # the histogram is log-scaled: the tallest bin reaches the top, an empty one the axis
    heights = [float(seg.split(",")[1]) for seg in c["bars"].split("L")[1:-1:2]]
    assert heights[1] == pytest.approx(TOP)
    assert heights[2] == pytest.approx(base)
    ratio = (base - heights[3]) / (base - heights[1])
    assert ratio == pytest.approx(np.log10(11) / np.log10(1001), abs=0.01)
    # label structures have no curve
    labelled = StructureSpec((*SPEC.structures, Structure("l", 0.5, (0, 0, 1), label=3)))
    assert len(tf_chart(HIST, labelled)["structures"]) == 2


def test_dropped_range_end_is_clamped_to_its_neighbours_and_the_other_end():
    assert dropped_edit(HIST, SPEC, index=0, kind="hi", fx=_fx(30), fy=0.5) == {
        "value_range": (10.0, 30.0)
    }
    # past the next structure's range: it stops where b starts (ranges may touch)
    assert dropped_edit(HIST, SPEC, index=0, kind="hi", fx=_fx(75), fy=0.5) == {
        "value_range": (10.0, 60.0)
    }
    # b's low end cannot pass a's high end, nor its own high end
    assert dropped_edit(HIST, SPEC, index=1, kind="lo", fx=_fx(5), fy=0.5)["value_range"] == (
        50.0,
        90.0,
    )
    lo, hi = dropped_edit(HIST, SPEC, index=1, kind="lo", fx=_fx(99), fy=0.5)["value_range"]
    assert (lo, hi) == (89.0, 90.0)
    # beyond the chart: the volume's range
    assert dropped_edit(HIST, SPEC, index=1, kind="hi", fx=1.0, fy=0.5) == {
        "value_range": (60.0, 100.0)
    }


def test_dropped_opacity_handle_sets_the_opacity():
    base = HEIGHT - BOTTOM
    fy = (TOP + (base - TOP) * 0.25) / HEIGHT  # a quarter down from the top
    assert dropped_edit(HIST, SPEC, index=0, kind="opacity", fx=0.3, fy=fy) == {"opacity": 0.75}
    assert dropped_edit(HIST, SPEC, index=0, kind="opacity", fx=0.3, fy=1.0) == {"opacity": 0.0}
    assert dropped_edit(HIST, SPEC, index=0, kind="opacity", fx=0.3, fy=-1) == {"opacity": 1.0}


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"index": 5, "kind": "lo", "fx": 0.5, "fy": 0.5}, "no structure 5"),
        ({"index": 0, "kind": "middle", "fx": 0.5, "fy": 0.5}, "unknown handle 'middle'"),
        ({"index": 0, "kind": "lo", "fx": "x", "fy": 0.5}, "bad handle position"),
        ({"index": 0, "kind": "lo", "fx": float("nan"), "fy": 0.5}, "bad handle position"),
    ],
)
def test_bad_drop_is_one_clear_error(kw, message):
    with pytest.raises(DVRInputError, match=message):
        dropped_edit(HIST, SPEC, **kw)


def test_colour_bar_covers_each_range_in_percent():
    stops = colour_bar_stops(SPEC, HIST)
    assert [(s["name"], s["start"], s["end"]) for s in stops] == [
        ("a", 10.0, 50.0),
        ("b", 60.0, 90.0),
    ]


@pytest.mark.parametrize("axis", ["+X", "-X", "+Y", "-Y", "+Z", "-Z"])
def test_axis_camera_looks_along_the_axis_at_the_centre(axis):
    cam = axis_camera((0, 10, 0, 20, 0, 30), axis, width=64, height=48)
    d = np.subtract(cam.position, cam.focal_point)
    k = "XYZ".index(axis[1])
    assert cam.focal_point == (5.0, 10.0, 15.0)
    assert np.sign(d[k]) == (1 if axis[0] == "+" else -1)
    assert np.count_nonzero(np.abs(d) > 1e-9) == 1
    assert abs(np.dot(d, cam.view_up)) < 1e-9
    assert (cam.width, cam.height) == (64, 48)


def test_axis_camera_refuses_an_unknown_axis():
    with pytest.raises(DVRInputError, match="view direction"):
        axis_camera((0, 1, 0, 1, 0, 1), "up", width=8, height=8)


def test_patient_view_of_a_file_without_orientation_notes_it_on_the_page():
    """The page's patient-side buttons show the same note as the CLI (on the info line)."""
    from functools import partial
    from types import SimpleNamespace

    from dvr_perception.app.session import Session
    from dvr_perception.app.tf_handlers import TFHandlers

    cams = []
    for oriented, expect in ((False, True), (True, False)):
        vol = Volume(np.zeros((4, 4, 4), np.uint8), source="head.nhdr", oriented=oriented)
        session = SimpleNamespace(volume=vol)
        session.patient_view_note = partial(Session.patient_view_note, session)
        page = SimpleNamespace(
            state=SimpleNamespace(info="", error=""),
            plotter=SimpleNamespace(window_size=(32, 24)),
            session=session,
            _set_camera=cams.append,
            fail=lambda msg: pytest.fail(msg),
        )
        TFHandlers.view_patient(page, "anterior")
        assert ("head.nhdr: the file records no patient orientation" in page.state.info) is expect
        # the fix named is the Data screen's control (the app can re-orient the file now)
        assert ("Data screen's Orientation field, e.g. LPI" in page.state.info) is expect
        assert "cannot re-orient" not in page.state.info
        assert page._view_name == "anterior"
    assert len(cams) == 2
    assert (cams[0].width, cams[0].height) == (32, 24)
