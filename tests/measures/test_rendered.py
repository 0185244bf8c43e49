"""Known answers of the three measures on volumes rendered by the ray-analysis engine.

The synthetic volumes are built so that every sample's class and opacity are known exactly:

* **Air is 70**, between the structure ranges: a structure *below* air (value 40, range
  ``(20, 55)``) and one *above* it (value 100, range ``(85, 255)``) both cross their range
  boundary exactly half-way between a structure voxel and an air voxel, and the trilinear
  transition from air never passes through the other structure's range.  (With air 0, every
  structure of higher value would wear a thin "skin" of the lower ranges.)
* ``edge=0``: the membership is 1 everywhere inside a range, so there are no ramps; a box of
  ``n`` voxels along the ray is sampled exactly where ``|z - centre| < n / 2``.
* Unshaded, ``sample_distance = 1`` voxel: each sample of a structure with opacity ``o`` has
  ``a = 1 - (1 - o) ** (1 / unit)`` (the opacity correction of ``structures/spec.py``), so a
  layer sampled ``n`` times lets ``(1 - a) ** n`` through.  The number of samples is counted
  from the engine's documented sample positions (``_grid.ray_segments``), not from its output.

The camera looks down ``-z`` (high ``z`` is in front).
"""

import dataclasses

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays import Camera, _grid
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.structures.spec import RenderSettings
from dvr_perception.volume import Volume

AIR, LOW, HIGH = 70, 40, 100
LOW_RANGE, HIGH_RANGE = (20, 55), (85, 255)
YELLOW, PURPLE = (1.0, 0.9, 0.2), (0.5, 0.2, 0.7)  # luminance 0.87 and 0.30 (Fig. 4c colours)
PX = 48


def structure(name, opacity, color, value):
    rng = LOW_RANGE if value == LOW else HIGH_RANGE
    return Structure(name, opacity, tuple(color), range=rng, edge=0.0)


def make_spec(*structures, background=(0.0, 0.0, 0.0), shade=False, unit=4.0):
    settings = RenderSettings(shade=shade, sample_distance=1.0, opacity_unit_distance=unit)
    return StructureSpec(tuple(structures), background=background, rendering=settings)


def parallel_camera(volume, size=PX, scale=None):
    """Parallel view down ``-z``; by default one pixel per voxel, rays through voxel centres.

    With rays through voxel centres no pixel sees a box edge half-covered, so every layer set
    is uniform (a half-covered fringe would bias the region means Metelli uses).
    """
    cam = Camera.from_view(volume.bounds, width=size, height=size)
    half = size / 2 if scale is None else scale
    return dataclasses.replace(cam, parallel_projection=True, parallel_scale=half)


def sample_opacity(opacity, unit=4.0):
    return 1.0 - (1.0 - opacity) ** (1.0 / unit)


def samples_in(volume, camera, z_lo, z_hi, row, col):
    """Samples of pixel (row, col) with ``z_lo - 0.5 < z < z_hi - 0.5`` (voxels z_lo..z_hi-1)."""
    seg = _grid.ray_segments(camera, volume, 1.0)
    i = row * camera.width + col
    z = seg["a"][i, 2] + (seg["t"][i] + np.arange(seg["n"][i])) * seg["b"][i, 2]
    lo, hi = z_lo - 0.5, z_hi - 0.5
    # the count is only a known answer if no sample sits on a class boundary
    assert np.min(np.abs(np.concatenate([z - lo, z - hi]))) > 0.05
    return int(np.count_nonzero((z > lo) & (z < hi)))


def ball(shape_zyx, centre, radius):
    z, y, x = np.indices(shape_zyx)
    cz, cy, cx = centre
    return (z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 <= radius**2


def run_all(volume, spec, camera):
    curvature, _ = curvature_volume(volume, spec)
    res = analyze(volume, spec, camera, curvature=curvature, build_cache=False)
    return res, visibility(res, spec), shape(res, spec), transparency(res, spec)


def finite_everywhere(*results):
    for r in results:
        for field in ("E_v", "E_s", "E_t"):
            if hasattr(r, field):
                assert np.isfinite(getattr(r, field))
        assert np.all(np.isfinite(r.deviation))


# -- (a) a uniform slab over a two-tone backdrop -------------------------------------------------
@pytest.mark.parametrize("background", [(0.0, 0.0, 0.0), (0.3, 0.3, 0.3)])
@pytest.mark.parametrize("opacity", [0.75, 0.4])
def test_slab_transmittance_matches_the_physical_one(background, opacity):
    """The two tones are the opaque wall and the background; the slab covers part of each.

    The wall lies behind the slab's left half, so the image shows {slab, wall}, {slab},
    {wall} and {} -- Metelli's P, Q, A and B -- and the perceived transmittance of the slab
    (Eq. 5; the regions are uniform, so TAP is undetermined and Eq. 8 is Metelli) must be the
    physical ``(1 - a) ** n``.
    """
    data = np.full((24, 32, 32), AIR, np.uint8)
    data[16:20, 4:28, 8:24] = LOW  # slab: 4 voxels deep, in front
    data[2:10, 8:24, 0:16] = HIGH  # opaque wall behind the left half
    vol = Volume(data)
    spec = make_spec(
        structure("slab", opacity, (0.8, 0.8, 0.8), LOW),
        structure("wall", 1.0, (0.2, 0.9, 0.4), HIGH),
        background=background,
    )
    cam = parallel_camera(vol)
    n = samples_in(vol, cam, 16, 20, PX // 2, PX // 2)
    assert n == 4
    expected = (1.0 - sample_opacity(opacity)) ** n
    res, vis, shp, trans = run_all(vol, spec, cam)
    finite_everywhere(vis, shp, trans)

    sets = {tuple(r["layers"]) for r in trans.regions}
    assert sets == {(), ("slab",), ("wall",), ("slab", "wall")}
    assert trans.relations[("slab", "wall")]["kind"] == "overlap"
    slab = trans.per_structure["slab"]
    assert slab["perceived_transparency"] == pytest.approx(expected, abs=0.03)
    for region in trans.regions:
        if "slab" in region["layers"]:
            assert region["method"]["slab"] == "metelli"
            assert region["transmittance"]["slab"] == pytest.approx(expected, abs=0.03)
    # the engine agrees: the slab's visible opacity is 1 - T where nothing is in front of it
    assert 1.0 - res.visible[0, PX // 2, PX // 2] == pytest.approx(expected, abs=1e-3)


# -- (b) layer relations -------------------------------------------------------------------------
def two_ball_volume(kind):
    dims = (24, 32, 32)
    data = np.full(dims, AIR, np.uint8)
    if kind == "overlap":  # separate in depth, overlapping in view
        data[ball(dims, (17, 16, 12), 5)] = LOW
        data[ball(dims, (6, 16, 20), 5)] = HIGH
    elif kind == "enclose":  # a ball inside a shell, with air between them
        data[ball(dims, (12, 16, 16), 10)] = LOW
        data[ball(dims, (12, 16, 16), 8)] = AIR
        data[ball(dims, (12, 16, 16), 5)] = HIGH
    else:  # disjoint
        data[ball(dims, (12, 16, 7), 5)] = LOW
        data[ball(dims, (12, 16, 25), 5)] = HIGH
    return Volume(data)


@pytest.mark.parametrize("kind", ["overlap", "enclose", "separate"])
@pytest.mark.parametrize("parallel", [True, False])
def test_sphere_relations(kind, parallel):
    vol = two_ball_volume(kind)
    spec = make_spec(
        structure("a", 0.5, YELLOW, LOW), structure("b", 0.5, PURPLE, HIGH), shade=True
    )
    cam = parallel_camera(vol) if parallel else Camera.from_view(vol.bounds, width=PX, height=PX)
    _, vis, shp, trans = run_all(vol, spec, cam)
    finite_everywhere(vis, shp, trans)
    relation = trans.relations[("a", "b")]
    assert relation["kind"] == kind
    assert relation["encloser"] == ("a" if kind == "enclose" else None)
    if kind == "separate":  # Case 1 everywhere: nothing layered, no deviation
        assert trans.E_t == 0.0
        assert all(not r["transmittance"] for r in trans.regions)


# -- (c) equal opacity, different colour (Fig. 4c) -----------------------------------------------
def metelli_pair(alpha, front, back, background):
    """Metelli transmittances ``(front, back)`` of two uniform layers of transmittance alpha.

    With luminances ``f``, ``b`` and background ``w``: ``I{} = w``, ``I{f} = alpha w + (1 -
    alpha) f``, ``I{b}`` likewise and ``I{f, b} = alpha I{b} + (1 - alpha) f``.  Eq. 5 gives the
    front layer ``alpha`` exactly and the back one ``1 - (1 - alpha) (b - w) / (f - w)``.
    """
    return alpha, 1.0 - (1.0 - alpha) * (back - background) / (front - background)


def lum(color):
    return 0.2126 * color[0] + 0.7152 * color[1] + 0.0722 * color[2]


@pytest.mark.parametrize("yellow_in_front", [True, False])
@pytest.mark.parametrize("white", [False, True])
def test_equal_opacity_layers_of_different_colour(yellow_in_front, white):
    """Which of two equally opaque layers is perceived as more opaque depends on the background.

    The paper (Fig. 4c) reports that the darker (purple) layer gets the lower transmittance.
    Under Metelli's model on rendered luminance that holds on a **light** background; on the
    default **black** background it is reversed: the layer with the larger luminance contrast
    to the background always gets the lower transmittance, whatever the depth order, and on
    black that is the brighter (yellow) one.
    """
    data = np.full((24, 32, 32), AIR, np.uint8)
    data[16:20, 8:24, 4:20] = LOW  # front layer, left
    data[4:8, 8:24, 12:28] = HIGH  # back layer, right; they overlap in the middle
    vol = Volume(data)
    front, back = (YELLOW, PURPLE) if yellow_in_front else (PURPLE, YELLOW)
    bg = (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)
    spec = make_spec(structure("front", 0.5, front, LOW), structure("back", 0.5, back, HIGH))
    spec = dataclasses.replace(spec, background=bg)
    cam = parallel_camera(vol)
    n_front = samples_in(vol, cam, 16, 20, PX // 2, PX // 2)
    n_back = samples_in(vol, cam, 4, 8, PX // 2, PX // 2)
    assert n_front == n_back == 4
    alpha = (1.0 - sample_opacity(0.5)) ** 4
    _, vis, shp, trans = run_all(vol, spec, cam)
    finite_everywhere(vis, shp, trans)
    assert trans.relations[("front", "back")]["kind"] == "overlap"
    perceived = {n: trans.per_structure[n]["perceived_transparency"] for n in ("front", "back")}
    exp_front, exp_back = metelli_pair(alpha, lum(front), lum(back), lum(bg))
    assert perceived["front"] == pytest.approx(exp_front, abs=0.02)
    # a back layer much brighter (or, on white, darker) than the front one gives Eq. 5 < 0:
    # no transparency percept; the measure clips it to 0 (fully opaque) and says so
    assert perceived["back"] == pytest.approx(max(exp_back, 0.0), abs=0.02)
    clipped = any("back" in r["clipped"] for r in trans.regions)
    assert clipped == (exp_back < 0)
    darker = "front" if lum(front) < lum(back) else "back"
    brighter = "back" if darker == "front" else "front"
    lower = darker if white else brighter
    higher = brighter if white else darker
    assert perceived[lower] < perceived[higher] - 0.05


# -- (d) an opaque front structure --------------------------------------------------------------
def test_opaque_front_visibility_deviation():
    """Rays through an opaque front box see only it: ``delta_v = 2 c_back A_imp`` (D1).

    ``A`` is the assigned opacity ``n a`` of a structure on the ray (occlusion ignored): both
    are thick enough for full presence, so the target composition is the importance ratio,
    ``c_back = 0.5 / 1.5``.  The front shows ``A_imp`` (the ray's opacity at the importances)
    where it should show ``(1 - c_back) A_imp``, the back 0 instead of ``c_back A_imp``.
    Rays through the back structure alone have ``delta_v = 0``.
    """
    data = np.full((24, 32, 32), AIR, np.uint8)
    data[16:18, 8:24, 8:24] = LOW  # opaque front box, 2 voxels deep
    data[4:8, 4:28, 4:28] = HIGH  # back box, 4 voxels deep, wider
    vol = Volume(data)
    unit = 1.0
    spec = make_spec(
        structure("front", 1.0, (0.8, 0.8, 0.8), LOW),
        structure("back", 0.5, (0.2, 0.9, 0.4), HIGH),
        unit=unit,
    )
    cam = parallel_camera(vol)
    c = PX // 2
    a_front = samples_in(vol, cam, 16, 18, c, c) * sample_opacity(1.0, unit)
    a_back = samples_in(vol, cam, 4, 8, c, c) * sample_opacity(0.5, unit)
    assert (a_front, a_back) == (2.0, 2.0)
    res, vis, shp, trans = run_all(vol, spec, cam)
    finite_everywhere(vis, shp, trans)
    through_front = res.visible[0] > 0.99
    back_only = (res.visible[1] > 0.05) & (res.visible[0] == 0)
    assert through_front.sum() > 100
    assert back_only.sum() > 100
    c_back = 0.5 * (1 - np.exp(-a_back / 0.05))
    c_back /= 1.0 * (1 - np.exp(-a_front / 0.05)) + c_back
    assert c_back == pytest.approx(1 / 3)
    expected = 2.0 * c_back * res.importance_accumulated[through_front]
    assert expected.min() > 0.66  # the rays are opaque
    np.testing.assert_allclose(vis.deviation[through_front], expected, atol=2e-3)
    np.testing.assert_allclose(vis.deviation[back_only], 0.0, atol=2e-3)


# -- (e) degenerate scenes ----------------------------------------------------------------------
def base_volume():
    data = np.full((24, 32, 32), AIR, np.uint8)
    data[16:20, 4:28, 8:24] = LOW
    data[2:10, 8:24, 0:16] = HIGH
    return Volume(data)


def test_structure_absent_from_the_volume():
    vol = base_volume()
    ghost = Structure("ghost", 0.5, (1.0, 0.0, 0.0), range=(200, 250), edge=0.0)
    spec = make_spec(
        structure("slab", 0.5, (0.8, 0.8, 0.8), LOW),
        Structure("wall", 1.0, (0.2, 0.9, 0.4), range=(85, 150), edge=0.0),
        ghost,
    )
    _, vis, shp, trans = run_all(vol, spec, parallel_camera(vol))
    finite_everywhere(vis, shp, trans)
    assert vis.per_structure["ghost"]["rays"] == 0
    assert vis.per_structure["ghost"]["visible_share"] == 0.0
    assert trans.per_structure["ghost"]["perceived_transparency"] is None
    assert all(("ghost" not in pair) for pair in trans.relations)
    # the absent structure changes nothing for the others
    assert trans.per_structure["slab"]["perceived_transparency"] == pytest.approx(0.5, abs=0.03)


def test_camera_sees_one_structure():
    """A window onto the middle of a wide flat slab: uniform image, one structure in view.

    The wall (behind a corner) is out of view; the slab's edges, whose smoothed curvature is
    not 0, are more than 6 voxels away, so the curvature seen is the float rounding of a flat
    face (~1e-8), which the shape measure must treat as 0, not normalise up to 1.
    """
    data = np.full((24, 32, 32), AIR, np.uint8)
    data[16:20, 2:30, 2:30] = LOW
    data[2:10, 0:6, 0:6] = HIGH
    vol = Volume(data)
    spec = make_spec(
        structure("slab", 0.5, (0.8, 0.8, 0.8), LOW), structure("wall", 1.0, PURPLE, HIGH)
    )
    cam = parallel_camera(vol, size=32, scale=3.0)
    cam = dataclasses.replace(cam, focal_point=(20.0, 16.0, 11.5), position=(20.0, 16.0, 80.0))
    res, vis, shp, trans = run_all(vol, spec, cam)
    finite_everywhere(vis, shp, trans)
    assert np.all(res.visible[1] == 0)
    assert np.all(res.visible[0] > 0.05)
    assert vis.E_v == pytest.approx(0.0, abs=1e-6)  # one structure per ray: shares agree
    assert trans.relations == {}
    assert trans.E_t == 0.0
    assert any("no region has a determinable layer transmittance" in n for n in trans.notes)
    assert trans.per_structure["wall"]["perceived_transparency"] is None
    assert shp.E_s == 0.0  # flat slab, uniform image: no curvature, no gradient


def test_empty_image():
    vol = Volume(np.full((16, 16, 16), AIR, np.uint8))
    spec = make_spec(structure("slab", 0.5, YELLOW, LOW), structure("wall", 1.0, PURPLE, HIGH))
    res, vis, shp, trans = run_all(vol, spec, parallel_camera(vol, size=32))
    finite_everywhere(vis, shp, trans)
    assert np.all(res.accumulated == 0)
    assert (vis.E_v, shp.E_s, trans.E_t) == (0.0, 0.0, 0.0)
    assert any("E_v = 0" in n for n in vis.notes)
    assert any("E_s = 0" in n for n in shp.notes)
    assert any("no non-empty region" in n for n in trans.notes)
    assert [r["kind"] for r in trans.regions] == ["empty"]


def test_luminance_is_shared_by_the_measures_of_one_analysis_but_follows_the_background():
    """Shape and transparency reuse one analysis's luminance; another background is new."""
    from dvr_perception.measures.results import _image_luminance

    vol = base_volume()
    spec = make_spec(structure("slab", 0.5, (0.8, 0.8, 0.8), LOW))
    cam = parallel_camera(vol)
    a = analyze(vol, spec, cam, build_cache=True)
    y, _ = _image_luminance(a, spec, a.accumulated.shape)
    again, _ = _image_luminance(a, spec, a.accumulated.shape)
    assert again is y
    assert not y.flags.writeable
    white = dataclasses.replace(spec, background=(1.0, 1.0, 1.0))
    y_white, _ = _image_luminance(a, white, a.accumulated.shape)
    empty = a.accumulated < 1e-6
    assert empty.any()
    assert np.all(y[empty] == 0.0)
    assert np.allclose(y_white[empty], 1.0)
    b = analyze(
        vol, spec, cam, build_cache=True
    )  # a new analysis is computed afresh, equal to the old one
    y_b, _ = _image_luminance(b, spec, b.accumulated.shape)
    assert y_b is not y
    assert np.array_equal(y_b, y)


def test_checked_fields_are_shared_by_the_measures_and_give_the_same_answers():
    """The measures of one engine analysis check its fields once; results do not change."""
    from types import SimpleNamespace

    from dvr_perception.measures.results import _accumulated, _visible

    vol = base_volume()
    spec = make_spec(
        structure("low", 0.4, (0.9, 0.3, 0.2), LOW), structure("high", 0.9, (0.2, 0.4, 1.0), HIGH)
    )
    a = analyze(vol, spec, parallel_camera(vol), build_cache=True)
    acc = _accumulated(a)
    assert _accumulated(a) is acc
    assert _visible(a, acc) is _visible(a, acc)
    assert not acc.flags.writeable
    assert not _visible(a, acc).flags.writeable
    fields = ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature")
    plain = SimpleNamespace(names=a.names, **{f: np.array(getattr(a, f)) for f in fields})
    assert _accumulated(plain) is not _accumulated(plain)  # other objects: checked each time
    # (the plain object has no share properties: its shares come from float64 division)
    v_a, v_p = visibility(a, spec), visibility(plain, spec)
    assert v_a.E_v == pytest.approx(v_p.E_v, abs=1e-6)
    assert v_a.E_v > 0.01
    t_a, t_p = transparency(a, spec), transparency(plain, spec)
    assert t_a.E_t == pytest.approx(t_p.E_t, abs=1e-6)
    assert len(t_a.regions) == len(t_p.regions) > 1


def test_engine_analyses_are_read_without_checks_and_others_are_checked():
    """The engine's own analyses skip the field checks (read-only, same answers); copies do not."""
    from types import SimpleNamespace

    from dvr_perception.rays._results import engine_made

    vol = base_volume()
    spec = make_spec(
        structure("low", 0.4, (0.9, 0.3, 0.2), LOW), structure("high", 0.9, (0.2, 0.4, 1.0), HIGH)
    )
    a = analyze(vol, spec, parallel_camera(vol), build_cache=False)
    assert engine_made(a)
    fields = ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature",
              "importance_accumulated")  # fmt: skip
    for f in fields:
        with pytest.raises(ValueError, match="read-only"):
            getattr(a, f)[..., 0] = 0
    plain = SimpleNamespace(
        names=a.names,
        visible_share=a.visible_share,
        assigned_share=a.assigned_share,
        **{f: np.array(getattr(a, f)) for f in fields},
    )
    for measure in (visibility, shape, transparency):
        trusted, checked = measure(a, spec), measure(plain, spec)
        for name in ("E_v", "E_s", "E_t", "deviation", "notes"):
            if hasattr(trusted, name):
                np.testing.assert_array_equal(getattr(trusted, name), getattr(checked, name))
    bad = dataclasses.replace(a, visible=np.full(a.visible.shape, np.nan, np.float32))
    assert not engine_made(bad)  # a hand-made RayAnalysis is checked as any other object
    with pytest.raises(DVRInputError, match="visible must be finite"):
        visibility(bad, spec)
    bent = dataclasses.replace(a, curvature=-np.ones(a.curvature.shape, np.float32))
    with pytest.raises(DVRInputError, match="curvature must be non-negative"):
        shape(bent, spec)


# -- an enclosing layer against the view without it (enclosure="unoccluded") ---------------------
def shell_volume():
    """A hollow labelled box (label 1) around two opaque grey blocks (labels 2 and 3)."""
    data = np.zeros((24, 32, 32), np.uint8)
    labels = np.zeros(data.shape, np.uint8)
    labels[2:20, 4:28, 4:28] = 1
    labels[4:18, 6:26, 6:26] = 0  # hollow: walls 2 voxels thick, front wall z = 18..19
    labels[8:14, 10:22, 8:16] = 2
    labels[8:14, 10:22, 16:24] = 3
    return Volume(data, labels=labels)


def shell_spec(grey):
    settings = RenderSettings(shade=False, sample_distance=1.0, opacity_unit_distance=4.0)
    return StructureSpec(
        (
            Structure("shell", 0.5, (grey, grey, grey), label=1),
            Structure("light", 1.0, (0.3, 0.3, 0.3), label=2),
            Structure("dark", 1.0, (0.1, 0.1, 0.1), label=3),
        ),
        rendering=settings,
    )


@pytest.mark.parametrize("grey", [0.6, 0.9])
def test_unoccluded_enclosure_gives_the_tap_of_what_the_layer_covers(grey):
    """Known answer: opaque blocks of luminance 0.3 / 0.1 behind a front wall of transmittance T.

    Seen through the wall each pixel is ``T * Y + c`` with ``c = grey * (1 - T)``; the blocks'
    robust range is [0, 0.4] (mean 0.2, std 0.1), so the Michelson TAP ratio is
    ``0.2 T / (0.2 T + c)``.  A brighter wall (0.9) reads as less transparent (Fig. 9 effect).
    """
    vol = shell_volume()
    spec = shell_spec(grey)
    cam = parallel_camera(vol)
    a = analyze(vol, spec, cam, build_cache=True)
    n = samples_in(vol, cam, 18, 20, 16, 12)
    t = (1.0 - sample_opacity(0.5)) ** n
    expected = 0.2 * t / (0.2 * t + grey * (1.0 - t))
    res = transparency(a, spec, enclosure="unoccluded")
    assert res.relations[("shell", "light")]["kind"] == "enclose"
    assert res.per_structure["shell"]["perceived_transparency"] == pytest.approx(expected, abs=0.02)
    # "auto" reads the shell the same way when the analysis has a cache (D3)
    auto = transparency(a, spec, enclosure="auto")
    assert auto.per_structure["shell"]["perceived_transparency"] == pytest.approx(
        res.per_structure["shell"]["perceived_transparency"], abs=1e-3
    )
    plain = transparency(a, spec, enclosure="plain")  # the paper's Case 2: the plain view
    assert plain.per_structure["shell"]["perceived_transparency"] != pytest.approx(
        expected, abs=0.02
    )


def test_unoccluded_enclosure_needs_the_cache():
    vol = shell_volume()
    spec = shell_spec(0.6)
    # a copy the engine did not make: no cache and no volume to walk again
    a = dataclasses.replace(analyze(vol, spec, parallel_camera(vol), build_cache=False))
    with pytest.raises(DVRInputError, match="build_cache=True"):
        transparency(a, spec, enclosure="unoccluded")
    with pytest.raises(DVRInputError, match="enclosure"):
        transparency(a, spec, enclosure="behind")
