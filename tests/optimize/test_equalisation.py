"""Visibility equalisation on real data (D1): cthead's bone gets the picture its importance asks."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from dvr_perception.optimize import optimize
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.io import load_spec
from dvr_perception.volume.io import load_volume

REPO = Path(__file__).resolve().parents[2]

PX = 64


@pytest.fixture(scope="module")
def cthead(shared_data):
    vol = load_volume(shared_data / "cthead.nhdr")
    spec = load_spec(REPO / "state_files" / "cthead.json")
    az, el, zoom = spec.view
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=PX, height=PX)
    return vol, spec, cam


def _with_bone(spec, importance):
    return replace(
        spec,
        structures=tuple(
            replace(s, importance=importance) if s.name == "bone" else s for s in spec.structures
        ),
    )


@pytest.fixture(scope="module")
def runs(cthead):
    vol, spec, cam = cthead
    return {
        imp: optimize(vol, _with_bone(spec, imp), cam, stages=("opacity",), seed=0)
        for imp in (0.4, 0.7)
    }


def test_the_skull_shows_through_the_face(runs):
    """The preset (skin 0.15, soft tissue 0.35, bone 0.7, fillings 1): the bone hidden behind
    skin and soft tissue (5 % of the picture against a target of about 30 %) is revealed."""
    r = runs[0.7]
    assert r.final["E_v"] <= 0.8 * r.initial["E_v"]
    assert r.final["coverage"] >= 0.6 * r.initial["coverage"]  # no wash-out (D6)
    before, after = r.initial["visible_share"], r.final["visible_share"]
    target = r.initial["target_share"]
    assert before["bone"] < 0.1 < 0.25 < target["bone"]
    assert after["bone"] - before["bone"] >= 0.5 * (target["bone"] - before["bone"])
    assert after["fillings"] >= before["fillings"]  # the most important never loses share
    assert r.structures["bone"]["share_after"] == after["bone"]
    assert "covered bone" in r.structures["soft tissue"]["reason"]


def test_more_importance_gives_more_of_the_picture(runs):
    """Importance is how much of the picture a structure should get: raising the bone's
    importance raises its target share and the share the optimiser gives it."""
    low, high = runs[0.4], runs[0.7]
    assert high.initial["target_share"]["bone"] > low.initial["target_share"]["bone"] + 0.05
    assert high.final["visible_share"]["bone"] > low.final["visible_share"]["bone"] + 0.03
    for r in (low, high):
        assert r.final["E"] <= r.initial["E"]
