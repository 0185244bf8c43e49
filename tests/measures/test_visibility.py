"""Tests for dvr_perception.measures.visibility on hand-built ray analyses."""

from types import SimpleNamespace

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.measures import VisibilityResult, visibility
from dvr_perception.structures.spec import Structure, StructureSpec


def two_structure_analysis(w_front=0.6, w_back=0.2):
    """2x2 image: column 0 rays meet an opaque front structure then the back one;
    column 1 rays meet only the back structure (opacity 0.5); row 1 of column 1 is empty."""
    visible = np.zeros((2, 2, 2))
    assigned = np.zeros((2, 2, 2))
    visible[0, :, 0] = 1.0  # opaque front hides the back completely
    assigned[0, :, 0] = w_front
    assigned[1, :, 0] = w_back
    visible[1, 0, 1] = 0.5
    assigned[1, 0, 1] = w_back
    accumulated = visible.sum(axis=0)
    present = np.array([[3, 2], [3, 0]], dtype=np.uint32)
    return SimpleNamespace(
        visible=visible,
        assigned=assigned,
        accumulated=accumulated,
        present=present,
        names=("front", "back"),
    )


def spec_for(names, importances):
    return StructureSpec(
        structures=tuple(
            Structure(name=n, importance=w, color=(1.0, 1.0, 1.0), range=(i, i + 1))
            for i, (n, w) in enumerate(zip(names, importances, strict=True))
        )
    )


def test_opaque_front_gives_analytic_deviation():
    w_f, w_b = 0.6, 0.2
    res = visibility(two_structure_analysis(w_f, w_b))
    assert isinstance(res, VisibilityResult)
    expected = 2 * w_b / (w_f + w_b)  # |1 - 0.75| + |0 - 0.25|
    assert res.deviation[0, 0] == pytest.approx(expected)
    assert res.deviation[1, 0] == pytest.approx(expected)
    assert res.deviation[0, 1] == 0.0  # the back structure alone: shares agree
    assert res.deviation[1, 1] == 0.0  # empty ray
    assert res.deviation.dtype == np.float32
    np.testing.assert_array_equal(res.nonempty, [[True, True], [True, False]])
    assert res.E_v == pytest.approx(2 * expected / 3)
    assert res.notes == ()


def test_per_structure_shares_and_histograms():
    res = visibility(two_structure_analysis(), bins=5)
    np.testing.assert_allclose(res.bin_edges, [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    front, back = res.per_structure["front"], res.per_structure["back"]
    # image-wide: sum visible / sum accumulated = 2 / 2.5, sum assigned share 1.2 / 1.8
    assert front["visible_share"] == pytest.approx(2 / 2.5)
    assert back["visible_share"] == pytest.approx(0.5 / 2.5)
    assert front["assigned_share"] == pytest.approx(1.2 / 1.8)
    assert back["assigned_share"] == pytest.approx(0.6 / 1.8)
    # front present on 2 rays, visible share 1 (last bin), assigned share 0.75
    np.testing.assert_array_equal(front["histogram_visible"], [0, 0, 0, 0, 2])
    np.testing.assert_array_equal(front["histogram_assigned"], [0, 0, 0, 2, 0])
    # back present on 3 rays: visible shares 0, 0, 1; assigned shares 0.25, 0.25, 1
    np.testing.assert_array_equal(back["histogram_visible"], [2, 0, 0, 0, 1])
    np.testing.assert_array_equal(back["histogram_assigned"], [0, 2, 0, 0, 1])
    assert (front["rays"], back["rays"]) == (2, 3)


def test_single_structure_has_zero_deviation():
    rng = np.random.default_rng(0)
    vis = rng.uniform(0.0, 1.0, (1, 3, 4))
    ana = SimpleNamespace(visible=vis, assigned=vis * 0.3, accumulated=vis[0], names=("only",))
    res = visibility(ana, spec_for(["only"], [0.3]))
    assert res.E_v == 0.0
    assert not res.deviation.any()


def test_no_nonempty_ray_gives_zero_with_note():
    ana = SimpleNamespace(
        visible=np.zeros((2, 3, 3)),
        assigned=np.zeros((2, 3, 3)),
        accumulated=np.zeros((3, 3)),
        names=("a", "b"),
    )
    res = visibility(ana)
    assert res.E_v == 0.0
    assert not res.nonempty.any()
    assert any("E_v = 0" in n for n in res.notes)
    assert res.per_structure["a"]["visible_share"] == 0.0
    assert res.per_structure["a"]["histogram_visible"].sum() == 0


def test_share_properties_are_used_when_present():
    ana = two_structure_analysis()
    # a deliberately different visible share: both structures seen as intended everywhere
    ana.visible_share = ana.assigned / np.maximum(ana.assigned.sum(axis=0), 1e-12)
    res = visibility(ana)
    assert res.E_v == pytest.approx(0.0, abs=1e-12)


def test_worst_case_is_two():
    # the intended structure is invisible, an unintended one is seen
    ana = SimpleNamespace(
        visible=np.array([[[0.0]], [[0.7]]]),
        assigned=np.array([[[0.5]], [[0.0]]]),
        accumulated=np.array([[0.7]]),
        names=("wanted", "unwanted"),
    )
    assert visibility(ana).E_v == pytest.approx(2.0)


def test_bad_input():
    ana = two_structure_analysis()
    with pytest.raises(DVRInputError, match="bins"):
        visibility(ana, bins=0)
    with pytest.raises(DVRInputError, match="names"):
        visibility(ana, spec_for(["x", "y"], [0.5, 0.5]))
    bad = SimpleNamespace(**vars(ana))
    bad.assigned = np.zeros((2, 3, 3))
    with pytest.raises(DVRInputError, match=r"analysis\.assigned"):
        visibility(bad)
    bad = SimpleNamespace(**vars(ana))
    bad.visible = np.full((2, 2, 2), np.nan)
    with pytest.raises(DVRInputError, match=r"analysis\.visible"):
        visibility(bad)
    bad = SimpleNamespace(**vars(ana))
    del bad.accumulated
    with pytest.raises(DVRInputError, match=r"analysis\.accumulated is missing"):
        visibility(bad)


def test_inconsistent_visible_sum_warns():
    ana = two_structure_analysis()
    ana.accumulated = ana.accumulated * 0.5
    with pytest.warns(DVRWarning, match="does not sum"):
        visibility(ana)
