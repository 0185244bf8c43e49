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
            Structure(name=n, importance=w, colour=(1.0, 1.0, 1.0), range=(i, i + 1))
            for i, (n, w) in enumerate(zip(names, importances, strict=True))
        )
    )


def presence(a, scale=0.05):
    return 1.0 - np.exp(-a / scale)


def test_opaque_front_gives_analytic_deviation():
    w_f, w_b = 0.6, 0.2
    res = visibility(two_structure_analysis(w_f, w_b))  # no spec: equal importances
    assert isinstance(res, VisibilityResult)
    c_b = presence(w_b) / (presence(w_f) + presence(w_b))  # back's target composition
    expected = 2 * c_b  # |c_f * 1 - 1| + |c_b * 1 - 0| with A_imp = 1
    assert res.deviation[0, 0] == pytest.approx(expected)
    assert res.deviation[1, 0] == pytest.approx(expected)
    assert res.deviation[0, 1] == 0.0  # the back structure alone: target = visible = 0.5
    assert res.deviation[1, 1] == 0.0  # empty ray
    assert res.deviation.dtype == np.float32
    np.testing.assert_array_equal(res.nonempty, [[True, True], [True, False]])
    assert res.E_v == pytest.approx(2 * expected / 3)
    assert res.composition == "importance"
    assert any("A_imp = accumulated" in n for n in res.notes)


def test_importance_weights_the_target_and_thickness_is_an_option():
    ana = two_structure_analysis(0.6, 0.2)
    spec = spec_for(["front", "back"], [0.2, 0.8])  # the thin back structure matters more
    res = visibility(ana, spec)
    wf, wb = 0.2 * presence(0.6), 0.8 * presence(0.2)
    assert res.target[1, 0, 0] == pytest.approx(wb / (wf + wb), rel=1e-6)
    assert res.deviation[0, 0] == pytest.approx(2 * wb / (wf + wb), rel=1e-6)
    thick = visibility(ana, spec, composition="thickness")
    assert thick.target[1, 0, 0] == pytest.approx(0.2 / 0.8, rel=1e-6)  # 0.25: thickness
    assert thick.deviation[0, 0] == pytest.approx(2 * 0.25, rel=1e-6)
    assert thick.E_v < res.E_v  # the importance target asks more of the hidden structure
    with pytest.raises(DVRInputError, match="composition"):
        visibility(ana, composition="share")
    with pytest.raises(DVRInputError, match="presence_scale"):
        visibility(ana, presence_scale=0.0)


def test_a_grazing_ray_does_not_count_as_full_presence():
    # ray 0 crosses both thickly; ray 1 only grazes the back structure (assigned 0.005)
    assigned = np.array([[[1.0, 1.0]], [[1.0, 0.005]]])
    visible = np.array([[[0.5, 0.5]], [[0.5, 0.0]]])
    ana = SimpleNamespace(visible=visible, assigned=assigned, accumulated=visible.sum(0),
                          importance_accumulated=np.ones((1, 2)), names=("a", "b"))  # fmt: skip
    res = visibility(ana, spec_for(["a", "b"], [0.5, 0.5]))
    np.testing.assert_allclose(res.target[:, 0, 0], [0.5, 0.5], rtol=1e-6)
    p = presence(0.005)  # ~0.095
    np.testing.assert_allclose(res.target[:, 0, 1], [1 / (1 + p), p / (1 + p)], rtol=1e-6)


def test_per_structure_shares_and_histograms():
    res = visibility(two_structure_analysis(), bins=5)
    np.testing.assert_allclose(res.bin_edges, [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    front, back = res.per_structure["front"], res.per_structure["back"]
    c_b = presence(0.2) / (presence(0.6) + presence(0.2))
    # image-wide: sum visible over all structures 2.5; sum target 1 + 1 + 0.5
    assert front["visible_share"] == pytest.approx(2 / 2.5)
    assert back["visible_share"] == pytest.approx(0.5 / 2.5)
    assert front["target_share"] == pytest.approx(2 * (1 - c_b) / 2.5)
    assert back["target_share"] == pytest.approx((2 * c_b + 0.5) / 2.5)
    assert front["assigned_share"] == pytest.approx(1.2 / 1.8)  # thickness, for the report
    assert back["assigned_share"] == pytest.approx(0.6 / 1.8)
    assert back["visible_opacity"] == pytest.approx(0.5 / 3)  # mean over the 3 non-empty rays
    # front present on 2 rays, visible 1 (last bin), target 1 - c_b ~ 0.5 (bin 2)
    np.testing.assert_array_equal(front["histogram_visible"], [0, 0, 0, 0, 2])
    np.testing.assert_array_equal(front["histogram_assigned"], [0, 0, 2, 0, 0])
    # back present on 3 rays: visible 0, 0, 0.5; targets c_b, c_b, 0.5
    np.testing.assert_array_equal(back["histogram_visible"], [2, 0, 1, 0, 0])
    np.testing.assert_array_equal(back["histogram_assigned"], [0, 0, 3, 0, 0])
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


def test_fading_raises_E_v():
    # one structure; rendered at its importance the ray shows A_imp = 0.8: delta 0
    base = {"assigned": np.full((1, 1, 1), 0.9), "importance_accumulated": np.full((1, 1), 0.8),
                "names": ("only",)}  # fmt: skip
    at = SimpleNamespace(visible=np.full((1, 1, 1), 0.8), accumulated=np.full((1, 1), 0.8), **base)
    faded = SimpleNamespace(visible=np.full((1, 1, 1), 0.2), accumulated=np.full((1, 1), 0.2),
                            **base)  # fmt: skip
    assert visibility(at).E_v == pytest.approx(0.0)
    assert visibility(faded).E_v == pytest.approx(0.6)  # |0.8 - 0.2|: no trivial minimiser


def test_importance_accumulated_is_checked():
    ana = two_structure_analysis()
    ana.importance_accumulated = np.full((3, 3), 0.5)
    with pytest.raises(DVRInputError, match="importance_accumulated"):
        visibility(ana)


def test_worst_case_is_two():
    # the intended structure is invisible, an unintended one is seen, on an opaque ray
    ana = SimpleNamespace(
        visible=np.array([[[0.0]], [[1.0]]]),
        assigned=np.array([[[0.5]], [[0.0]]]),
        accumulated=np.array([[1.0]]),
        importance_accumulated=np.array([[1.0]]),
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
