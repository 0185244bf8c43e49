"""The optimiser's reasons in words (dvr_perception.optimize.explain)."""

from __future__ import annotations

import numpy as np

from dvr_perception.optimize.explain import explain, explanation_line

NAMES = ["skin", "bone", "teeth"]


def _explain(ops_after, after, copresence=None):
    before = {"skin": 0.80, "bone": 0.05, "teeth": 0.15}
    target = {"skin": 0.40, "bone": 0.30, "teeth": 0.30}
    return explain(NAMES, [0.5, 0.7, 0.9], ops_after, before, after, target, copresence)


def test_lowered_names_what_it_covered_and_raised_what_it_lacked():
    out = _explain([0.2, 0.7, 1.0], {"skin": 0.5, "bone": 0.25, "teeth": 0.25})
    # bone needed the most (0.25 short) and gained: the skin covered it
    assert out["skin"]["reason"] == (
        "lowered: it covered bone, which had 5 % of the picture against a target of 30 %"
    )
    assert out["teeth"]["reason"] == ("raised: it had 15 % of the picture against a target of 30 %")
    assert out["bone"]["reason"].startswith("kept: the other changes moved its share from 5 %")
    line = explanation_line("skin", out["skin"])
    assert line.startswith("skin: opacity 0.50 -> 0.20; share of the picture 80 % -> target")
    assert line.endswith("40 % -> 50 %; " + out["skin"]["reason"])


def test_only_structures_on_the_same_rays_count_as_covered():
    co = np.array([[1.0, 0.0, 0.6], [0.0, 1.0, 0.0], [0.6, 0.0, 1.0]])  # skin never meets bone
    out = _explain([0.2, 0.7, 1.0], {"skin": 0.5, "bone": 0.25, "teeth": 0.25}, co)
    assert "covered teeth" in out["skin"]["reason"]
    none = np.eye(3)  # nothing shares a ray: the skin had more than its target
    out = _explain([0.2, 0.7, 1.0], {"skin": 0.5, "bone": 0.25, "teeth": 0.25}, none)
    assert out["skin"]["reason"] == ("lowered: it had 80 % of the picture against a target of 40 %")


def test_small_changes_are_kept():
    out = _explain([0.505, 0.7, 0.9], {"skin": 0.8, "bone": 0.05, "teeth": 0.15})
    for name in NAMES:
        assert out[name]["reason"].startswith("kept: it has")
        assert out[name]["opacity_before"] != 0
        assert out[name]["target_share"] > 0
