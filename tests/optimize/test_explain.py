"""The optimiser's reasons in words (dvr_perception.optimize.explain, issues 16 and 30).

Small hand-made cases: who covers whom, shares before, after and target, materials and
colours before and after; then the reasons on optimised volumes (two slabs one behind the
other, the phantom).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from dvr_perception.optimize import optimize
from dvr_perception.optimize._exact import OpacityModel
from dvr_perception.optimize._problem import Params, Problem
from dvr_perception.optimize.explain import explain, explanation_line, explanation_lines
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import make_phantom
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume

#: The measures' names and status codes, which the default words never use.
JARGON = re.compile(r"\bE_[vst]\b|\bE\b|Eq\. ?13|\bS \(|status \d|max_iter|StopIteration")


def _links(out: dict) -> dict:
    """``{structure: structure it was lowered for}`` read from the reasons' words."""
    names = list(out)
    found = {}
    for name, e in out.items():
        for other in names:
            if other != name and (
                f"covered {other}," in e["reason"] or f"traded for {other}," in e["reason"]
            ):
                found[name] = other
    return found


def _has_circle(links: dict) -> bool:
    for start in links:
        seen, cur = {start}, links[start]
        while cur in links:
            if cur in seen:
                return True
            seen.add(cur)
            cur = links[cur]
    return False


# -- opacity: one consistent reason per structure --------------------------------------------------
def test_two_structures_covering_each_other_make_no_circular_pair():
    """Muscle and heart each lie in front of the other somewhere (the chest): both were
    lowered, both below their target and both gained. Only one may say it covered the other:
    the one that hides more of the other (muscle), and the heart names its own reason."""
    names = ["muscle", "heart"]
    covers = [[0.0, 0.6], [0.2, 0.0]]  # the muscle hides three times more of the heart
    before = {"muscle": 0.16, "heart": 0.10}
    after = {"muscle": 0.29, "heart": 0.35}
    target = {"muscle": 0.31, "heart": 0.28}
    out = explain(names, [0.25, 0.60], [0.08, 0.36], before, after, target, covers)
    assert _links(out) == {"muscle": "heart"}
    assert "heart" in out["muscle"]["reason"]
    assert "muscle" not in out["heart"]["reason"]
    assert out["muscle"]["traded_for"] == "heart"
    assert out["heart"]["traded_for"] is None
    # the heart still says why, in its own terms: it was below its target too
    assert out["heart"]["reason"].startswith(
        "lowered: although it had less of the picture than its target (10 % against 28 %)"
    )


def test_three_structures_covering_in_a_ring_make_no_circle():
    """A covers B, B covers C, C covers A (all lowered, all below target, all gained): the
    strongest two links stay, the third would close a circle and is dropped."""
    names = ["a", "b", "c"]
    covers = [[0.0, 0.5, 0.0], [0.0, 0.0, 0.4], [0.3, 0.0, 0.0]]
    before = {"a": 0.1, "b": 0.1, "c": 0.1}
    after = {"a": 0.2, "b": 0.2, "c": 0.2}
    target = {"a": 0.33, "b": 0.33, "c": 0.34}
    out = explain(names, [0.8, 0.8, 0.8], [0.5, 0.5, 0.5], before, after, target, covers)
    links = _links(out)
    assert links == {"a": "b", "b": "c"}
    assert not _has_circle(links)


def test_no_circles_on_random_cases():
    """Whatever the covering, the reasons' links never form a circle."""
    rng = np.random.default_rng(7)
    names = [f"s{i}" for i in range(5)]
    for _ in range(200):
        covers = rng.uniform(0, 1, (5, 5)) * (rng.uniform(size=(5, 5)) < 0.7)
        ops0 = rng.uniform(0.2, 1.0, 5)
        ops1 = np.clip(ops0 - rng.uniform(-0.2, 0.6, 5), 0.01, 1.0)
        b, a, t = (rng.dirichlet(np.ones(5)) for _ in range(3))
        out = explain(names, ops0, ops1, *(dict(zip(names, x, strict=True)) for x in (b, a, t)),
                      covers)  # fmt: skip
        links = {n: e["traded_for"] for n, e in out.items() if e["traded_for"]}
        assert not _has_circle(links)
        assert _links(out) == links


def test_below_target_losing_opacity_names_the_trade():
    """Bone had 2 % of the picture against a target of 12 % and still lost opacity: it says
    so and names the structure behind it it was traded for; its share still rose."""
    names = ["muscle", "heart", "bone"]
    covers = [[0.0, 0.5, 0.1], [0.0, 0.0, 0.0], [0.0, 0.3, 0.0]]  # bone in front of heart
    before = {"muscle": 0.78, "heart": 0.20, "bone": 0.02}
    after = {"muscle": 0.57, "heart": 0.35, "bone": 0.08}
    target = {"muscle": 0.60, "heart": 0.28, "bone": 0.12}
    out = explain(names, [0.25, 0.6, 0.85], [0.08, 0.6, 0.55], before, after, target, covers)
    reason = out["bone"]["reason"]
    assert reason.startswith(
        "lowered: although it had less of the picture than its target (2 % against 12 %), "
        "it was traded for heart, which had less of the picture than its target (20 % against "
        "28 %) and lies behind it"
    )
    assert reason.endswith("its share still rose to 8 % as what lies in front of it faded")
    assert out["bone"]["traded_for"] == "heart"


def test_below_target_losing_opacity_without_anyone_behind_says_what_it_traded():
    """Nothing lies behind: the trade is its own over-showing where it shows (``over`` > 0),
    or, when it did not over-show, the picture as a whole."""
    names = ["skin", "bone"]
    before, after, target = (
        {"skin": 0.7, "bone": 0.3},
        {"skin": 0.72, "bone": 0.28},
        {
            "skin": 0.6,
            "bone": 0.4,
        },
    )
    covers = np.zeros((2, 2))
    out = explain(names, [0.3, 0.9], [0.3, 0.7], before, after, target, covers, over=[0.0, 0.2])
    assert out["bone"]["reason"] == (
        "lowered: although it had less of the picture than its target (30 % against 40 %), "
        "where it shows it took more of the picture than its importance asks for; its share "
        "fell to 28 %"
    )
    out = explain(names, [0.3, 0.9], [0.3, 0.7], before, after, target, covers, over=[0.0, -0.1])
    assert "the picture as a whole came closer to the intended shares" in out["bone"]["reason"]


def test_a_changed_opacity_is_never_kept():
    """ "kept" exactly when the two opacities print the same (two decimals)."""
    names = ["skin", "bone"]
    shares = {"skin": 0.5, "bone": 0.5}
    out = explain(names, [0.50, 0.70], [0.506, 0.703], shares, shares, shares)
    assert explanation_line("skin", out["skin"]).startswith("skin: opacity 0.50 -> 0.51;")
    assert not out["skin"]["reason"].startswith("kept")
    assert out["skin"]["reason"].startswith("raised")
    assert out["bone"]["reason"].startswith("kept")  # 0.70 -> 0.70
    rng = np.random.default_rng(3)
    for _ in range(300):
        o0 = rng.uniform(0, 1, 2)
        o1 = np.clip(o0 + rng.normal(0, 0.01, 2), 0, 1)
        b, a = rng.dirichlet([1, 1]), rng.dirichlet([1, 1])
        out = explain(names, o0, o1, dict(zip(names, b, strict=True)),
                      dict(zip(names, a, strict=True)), shares)  # fmt: skip
        for i, n in enumerate(names):
            printed_same = f"{o0[i]:.2f}" == f"{o1[i]:.2f}"
            assert out[n]["reason"].startswith("kept") == printed_same


def test_raised_and_above_target_reasons():
    names = ["skin", "bone", "teeth"]
    before = {"skin": 0.80, "bone": 0.05, "teeth": 0.15}
    after = {"skin": 0.5, "bone": 0.25, "teeth": 0.25}
    target = {"skin": 0.40, "bone": 0.30, "teeth": 0.30}
    none = np.zeros((3, 3))
    out = explain(names, [0.5, 0.7, 0.9], [0.2, 0.7, 1.0], before, after, target, none)
    assert out["teeth"]["reason"] == (
        "raised: it had less of the picture than its target (15 % against 30 %)"
    )
    assert out["skin"]["reason"] == (
        "lowered: it had more of the picture than its target (80 % against 40 %)"
    )
    assert out["bone"]["reason"] == (
        "kept: the other changes moved its share from 5 % to 25 % (target 30 %)"
    )
    line = explanation_line("skin", out["skin"])
    assert line == (
        "skin: opacity 0.50 -> 0.20; share of the picture 80 % -> 50 % (target 40 %); "
        + out["skin"]["reason"]
    )


# -- shading and colour --------------------------------------------------------------------------
MATERIALS = np.array([[0.3, 0.7, 0.2, 16.0], [0.2, 0.8, 0.2, 16.0], [0.2, 0.8, 0.2, 16.0]])


def _lighting(light_after=(0.0, 0.0, 1.0)):
    after = MATERIALS.copy()
    after[0, 0], after[0, 1] = 0.1, 0.9  # bone: more directional shading
    after[1, 2] = 0.5  # heart: stronger highlights
    return {
        "materials_before": MATERIALS, "materials_after": after,
        "light_before": (0.0, 0.0, 1.0), "light_after": light_after,
        "shape_before": np.array([0.40, 0.30, 0.50]),
        "shape_after": np.array([0.30, 0.36, 0.50]),
    }  # fmt: skip


def _colour():
    before = np.array([[1.0, 0.96, 0.84], [0.7, 0.3, 0.3], [0.7, 0.35, 0.3]])
    after = before.copy()
    after[1] = (0.7, 0.1, 0.1)  # heart: more saturated, away from the muscle's red-brown
    return {
        "colours_before": before, "colours_after": after,
        "transparency_before": np.array([0.02, 0.05, 0.04]),
        "transparency_after": np.array([0.02, 0.03, 0.04]),
    }  # fmt: skip


def _explain_stages(light_after=(0.0, 0.0, 1.0)):
    names = ["bone", "heart", "muscle"]
    shares = dict.fromkeys(names, 1 / 3)
    overlap = np.full((3, 3), 0.5)
    overlap[0, 1] = overlap[1, 0] = 0.0  # bone and heart never on the same rays
    return explain(names, [0.5] * 3, [0.5] * 3, shares, shares, shares, np.zeros((3, 3)),
                   lighting=_lighting(light_after), colour=_colour(),
                   overlap=overlap)  # fmt: skip


def test_lighting_lines_say_what_changed_and_why():
    out = _explain_stages()
    assert out["bone"]["shading"] == (
        "more directional shading; its shape reads better than under the old lighting"
    )
    assert out["heart"]["shading"] == (
        "stronger highlights; its shape reads a little less clearly than under the old "
        "lighting, traded for the shape of bone, which reads better"
    )
    assert out["muscle"]["shading"] is None  # nothing changed for it
    # the light moved up and to the left: said for every structure, with its shape's verdict
    d = np.array([-0.3, 0.3, 0.9])
    out = _explain_stages(tuple(d / np.linalg.norm(d)))
    assert out["bone"]["shading"].startswith(
        "more directional shading and the light moved 25 degrees toward the upper left (now "
        "from the upper left); its shape reads better than under the old lighting"
    )
    assert out["muscle"]["shading"] == (
        "the light moved 25 degrees toward the upper left (now from the upper left); its "
        "shape reads about as well as under the old lighting"
    )


def test_colour_lines_say_what_changed_and_why():
    out = _explain_stages()
    assert out["heart"]["colour"] == (
        "more saturated; it moved away from the colour of muscle, so the two are told apart "
        "where they overlap; how see-through it looks is closer to what is intended"
    )
    assert out["bone"]["colour"] is None
    assert out["muscle"]["colour"] is None
    lines = explanation_lines("heart", out["heart"])
    assert [line.split(":")[0] for line in lines] == ["heart", "shading", "colour"]
    assert explanation_line("heart", out["heart"]) == "; ".join(lines)


def test_jargon_only_when_verbose():
    out = _explain_stages()
    for name, e in out.items():
        plain = explanation_line(name, e)
        assert not JARGON.search(plain), plain
    heart = explanation_line("heart", out["heart"], verbose=True)
    assert "[E_s on its pixels 0.300 -> 0.360]" in heart
    assert "[E_t of its layers 0.0500 -> 0.0300]" in heart


# -- on optimised volumes --------------------------------------------------------------------------
def _slabs():
    """Two slabs across the whole view, one behind the other along the default view axis."""
    n = 24
    data = np.zeros((n, n, n), np.uint8)
    data[3:8] = 100
    data[n - 8 : n - 3] = 200
    spec = StructureSpec(
        (
            Structure("first", 0.2, (0.9, 0.8, 0.6), range=(80, 120)),
            Structure("second", 0.9, (1.0, 0.3, 0.2), range=(180, 220)),
        ),
        rendering=RenderSettings(shade=False),
    )
    return Volume(data), spec.with_opacities([0.9, 0.9])


def test_covering_is_directional_on_two_slabs():
    """Only the slab in front hides the one behind: its entry is positive, the reverse 0."""
    vol, spec = _slabs()
    cam = Camera.from_view(vol.bounds, width=16, height=16)
    problem = Problem(
        [analyze(vol, spec, cam, build_cache=True).cache], [None], spec, np.ones(3), {}, None
    )
    params = Params.from_spec(spec)
    covers, own = OpacityModel(problem, params).covering(params.opacities)
    front, back = (0, 1) if covers[0, 1] > covers[1, 0] else (1, 0)
    assert covers[front, back] > 0.05
    assert covers[back, front] == 0.0
    assert np.all(np.diag(covers) == 0.0)
    assert own.shape == (2,)
    # the front slab at 0.9 shows far more than its importance asks for (0.2 of the ray)
    assert own[front] > 0


def test_optimised_slabs_name_the_slab_behind():
    vol, spec = _slabs()
    cam = Camera.from_view(vol.bounds, width=16, height=16)
    res = optimize(vol, spec, cam, stages=("opacity",), max_iter=3)
    front = max(spec.names, key=lambda n: res.initial["visible_share"][n])
    back = next(n for n in spec.names if n != front)
    assert res.spec.structures[spec.names.index(front)].opacity < 0.9 - 0.05
    assert f"covered {back}," in res.structures[front]["reason"]
    assert front not in res.structures[back]["reason"]


@pytest.fixture(scope="module")
def phantom_run():
    vol, spec = make_phantom(size=32)
    cam = Camera.from_view(vol.bounds, width=40, height=40)
    return spec, optimize(vol, spec, cam, max_iter=5)


def test_phantom_shading_and_colour_lines_match_the_changes(phantom_run):
    """After the lighting and colour stages: a shading line exactly where a material or the
    light changed, a colour line where the colour changed; no circle; no jargon."""
    spec, res = phantom_run
    p0, p1 = Params.from_spec(spec), Params.from_spec(res.spec)
    moved = np.degrees(np.arccos(np.clip(p0.light @ p1.light, -1, 1))) >= 3.0
    shading = colour = 0
    for k, name in enumerate(spec.names):
        e = res.structures[name]
        d = np.abs(p1.lighting[k] - p0.lighting[k])
        changed = moved or d[0] > 0.02 or d[2] > 0.05 or (
            max(p0.lighting[k, 2], p1.lighting[k, 2]) >= 0.05
            and max(p1.lighting[k, 3] / p0.lighting[k, 3], p0.lighting[k, 3] / p1.lighting[k, 3])
            > 1.25
        )  # fmt: skip
        assert (e["shading"] is not None) == bool(changed), (name, e["shading"])
        shading += e["shading"] is not None
        colour += e["colour"] is not None
        if np.allclose(p0.colours[k], p1.colours[k]):
            assert e["colour"] is None
        line = explanation_line(name, e)
        assert not JARGON.search(line), line
    assert shading >= 1
    assert colour >= 1
    links = {n: e["traded_for"] for n, e in res.structures.items() if e["traded_for"]}
    assert not _has_circle(links)


def test_a_barely_visible_colour_change_is_still_said_with_its_reason():
    """The tooth's dentin moved by about 1 CIELAB unit (below a just noticeable difference,
    about 2.3): the colour line says so, and why (its shape read better in the new shade)."""
    names = ["dentin", "enamel"]
    shares = dict.fromkeys(names, 0.5)
    before = np.array([[0.95, 0.88, 0.70], [0.85, 0.92, 1.0]])
    after = np.array([[0.9387, 0.8677, 0.6853], [0.85, 0.92, 1.0]])
    colour = {
        "colours_before": before, "colours_after": after,
        "transparency_before": np.zeros(2), "transparency_after": np.zeros(2),
        "shape_before": np.array([0.40, 0.30]), "shape_after": np.array([0.35, 0.30]),
    }  # fmt: skip
    out = explain(names, [0.4, 0.9], [0.4, 0.9], shares, shares, shares, colour=colour)
    assert out["dentin"]["colour"] == (
        "a barely visible change; its shape reads better than in its old shade"
    )
    assert out["enamel"]["colour"] is None
    assert out["dentin"]["colour_verbose"].endswith(
        "[E_t of its layers 0.0000 -> 0.0000; E_s on its pixels 0.400 -> 0.350]"
    )
