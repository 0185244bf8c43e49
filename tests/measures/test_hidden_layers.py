"""Decision D3 (a hidden layer is opaque, not undetermined) and the Fig. 9 series after D2.

The shell phantom: a labelled sphere shell (label 1, radius 15..17 voxels) around two opaque
blobs of different colour (labels 2 and 3), unshaded, seen down ``-z`` with a parallel camera
through the voxel centres.  Footprints come from where the structures are (``assigned``), so the
shell *encloses* both blobs at every opacity, also when it hides them, and the covered pixels
where the blobs are hidden count as transmittance 0.  Against the view without the shell
(``enclosure="auto"`` with the analysis's cache: the TAP of ``covered_transmittance``) its
transparency falls strictly with its opacity; against its plain view (the paper's Case 2, the
default) the blobs have more contrast than the shell's own ring, so it reads 1 until it hides
them, and then 0.

Known answers: the blobs are Case 1 (no transmittance), so every counted region's ``delta_t``
is the shell's ``(1 - alpha_shell - o_shell)^2``; with the blobs hidden ``alpha_shell = 0`` and
``E_t = (1 - 0.3)^2 = 0.49`` exactly for an expected opacity of 0.3.
"""

from __future__ import annotations

import colorsys
import dataclasses
import itertools
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from dvr_perception.measures import covered_transmittance, transparency
from dvr_perception.rays import Camera
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.structures.io import load_spec
from dvr_perception.structures.spec import RenderSettings
from dvr_perception.volume import Volume
from dvr_perception.volume.io import load_volume
from tests.measures.test_transparency import analysis_and_spec

REPO = Path(__file__).resolve().parents[2]
OPACITIES = (0.05, 0.1, 0.2, 0.4, 0.7, 0.95)
EXPECTED = 0.3  # the shell's importance, hence its expected opacity, in every rendering


def ball(shape, centre, radius):
    z, y, x = np.indices(shape)
    return (z - centre[0]) ** 2 + (y - centre[1]) ** 2 + (x - centre[2]) ** 2 <= radius**2


def shell_scene(opacity):
    """The shell at rendering ``opacity`` (importance 0.3) around a yellow and a blue blob."""
    dims = (40, 40, 40)
    labels = np.zeros(dims, np.uint8)
    labels[ball(dims, (20, 20, 20), 17)] = 1
    labels[ball(dims, (20, 20, 20), 15)] = 0
    labels[ball(dims, (20, 20, 12), 5)] = 2
    labels[ball(dims, (20, 20, 28), 5)] = 3
    vol = Volume(np.zeros(dims, np.uint8), labels=labels)
    settings = RenderSettings(shade=False, sample_distance=1.0, opacity_unit_distance=2.0)
    spec = StructureSpec(
        (
            Structure("shell", EXPECTED, (0.5, 0.5, 0.5), label=1, opacity=opacity),
            Structure("yellow", 0.8, (0.8, 0.7, 0.3), label=2),
            Structure("blue", 0.8, (0.1, 0.2, 0.6), label=3),
        ),
        rendering=settings,
    )
    cam = Camera.from_view(vol.bounds, width=48, height=48)
    cam = dataclasses.replace(cam, parallel_projection=True, parallel_scale=24.0)
    return vol, spec, cam


def shell_alpha(res):
    return res.per_structure["shell"]["perceived_transparency"]


@pytest.fixture(scope="module")
def series():
    """``{opacity: (analysis, spec, result with "auto", default result)}``, with the cache."""
    out = {}
    for opacity in (*OPACITIES, EXPECTED, 1.0):
        vol, spec, cam = shell_scene(opacity)
        a = analyze(vol, spec, cam)
        out[opacity] = (a, spec, transparency(a, spec), transparency(a, spec, enclosure="plain"))
    return out


def test_the_shell_encloses_both_blobs_at_every_opacity(series):
    for opacity, (_, _, *results) in series.items():
        for res in results:
            assert res.relations[("shell", "yellow")]["kind"] == "enclose", opacity
            assert res.relations[("shell", "blue")]["kind"] == "enclose", opacity
            assert res.relations[("yellow", "blue")]["kind"] == "separate", opacity
            assert res.undetermined == []
            assert shell_alpha(res) is not None


def test_shell_transparency_falls_strictly_with_its_opacity(series):
    """Read against the view without it ("auto" with a cache): strictly falling."""
    alphas = [shell_alpha(series[o][2]) for o in OPACITIES]
    assert all(a is not None for a in alphas)
    assert all(a > b for a, b in itertools.pairwise(alphas)), alphas
    # the semi-transparent shell is read as covered_transmittance reads it (Fig. 9's TAP)
    for opacity in (0.1, 0.2, 0.4, 0.7):
        a, spec, res, _ = series[opacity]
        assert float(a.visible[1:].max()) > 0.05  # the blobs are seen
        tap = covered_transmittance(a, spec, "shell").alpha
        assert shell_alpha(res) == pytest.approx(min(tap, 1.0), abs=1e-6)
    assert alphas[0] > 0.95  # nearly clear
    assert alphas[-2] < 0.3  # 0.7: the blobs are barely seen through it


def test_by_default_the_shell_never_reads_more_transparent_as_it_grows_opaque(series):
    """The paper's plain-view TAP saturates at 1 while the blobs show, then hiding gives 0."""
    alphas = [shell_alpha(series[o][3]) for o in OPACITIES]
    assert all(a >= b for a, b in itertools.pairwise(alphas)), alphas
    assert alphas[:-1] == [1.0] * (len(OPACITIES) - 1)  # C(P) > C(ring): clipped to 1
    assert alphas[-1] == 0.0


@pytest.mark.parametrize("opacity", [0.95, 1.0])
def test_a_shell_hiding_the_blobs_is_opaque_not_undetermined(series, opacity):
    a, _, *results = series[opacity]
    assert float(a.visible[1:].max()) <= 0.05  # the blobs are not visible
    assert float(a.assigned[1:].max()) > 0.5  # but they are there
    for res in results:
        assert shell_alpha(res) == pytest.approx(0.0, abs=1e-12)
        assert {m for r in res.regions for m in r["method"].values()} == {"hidden"}
        assert res.E_t == pytest.approx((1.0 - 0.0 - EXPECTED) ** 2, abs=1e-12)


def test_hiding_raises_e_t(series):
    """Same expected opacities: hiding the blobs costs more than showing them at 0.3."""
    for i in (2, 3):  # "auto" and the default
        semi, hiding = series[EXPECTED][i].E_t, series[1.0][i].E_t
        assert semi <= 0.09 + 1e-9  # default: (1 - 1 - 0.3)^2 at most
        assert hiding == pytest.approx(0.49, abs=1e-12)
        assert hiding > semi + 0.39
        e_t = [series[o][i].E_t for o in OPACITIES]
        assert e_t[-1] == max(e_t)  # nothing is worse than hiding
    assert series[EXPECTED][2].E_t < 0.05  # read against the view without it: near its target


def test_without_the_cache_a_hiding_shell_is_still_opaque():
    """No re-evaluation cache: the view without the shell is walked again (D7), hidden pixels
    read 0, and E_t is the cache's."""
    results = {}
    for opacity in (EXPECTED, 1.0):
        vol, spec, cam = shell_scene(opacity)
        a = analyze(vol, spec, cam, build_cache=False)
        results[opacity] = transparency(a, spec, enclosure="auto")
        assert transparency(a, spec).E_t == results[opacity].E_t
        cached = transparency(analyze(vol, spec, cam, build_cache=True), spec)
        assert results[opacity].E_t == pytest.approx(cached.E_t, abs=1e-6)
    assert results[1.0].per_structure["shell"]["perceived_transparency"] == 0.0
    assert results[1.0].E_t == pytest.approx(0.49, abs=1e-12)
    assert results[EXPECTED].per_structure["shell"]["perceived_transparency"] > 0.5
    assert results[1.0].E_t > results[EXPECTED].E_t


def test_without_assigned_footprints_stay_visible_ones(series):
    """An analysis without ``assigned`` (hand-made) keeps the visible footprints: the hiding
    shell then stands alone (Case 1), as before D3."""
    a, spec, *_ = series[1.0]
    plain = SimpleNamespace(
        names=a.names, rgba=np.array(a.rgba), accumulated=np.array(a.accumulated),
        visible=np.array(a.visible),
    )  # fmt: skip
    res = transparency(plain, spec)
    assert res.relations == {}
    assert shell_alpha(res) is None


def test_undetermined_layers_do_not_lower_e_t():
    """A uniform encloser (undetermined) beside a measurable pair leaves E_t as the pair's."""
    h, w = 10, 22
    band = np.zeros((h, w), bool)
    band[3:5, 0:8] = True
    back = np.zeros((h, w), bool)
    back[:, 0:4] = True
    outer = np.zeros((h, w), bool)
    outer[1:9, 12:21] = True
    inner = np.zeros((h, w), bool)
    inner[3:7, 14:18] = True
    pair = [(band, 0.65, 0.5), (back, 0.8, 0.9)]
    names, imp = ["band", "backdrop", "inner", "outer"], [0.6, 0.8, 0.7, 0.4]
    nothing = np.zeros((h, w), bool)
    both, spec = analysis_and_spec(
        (h, w), [*pair, (inner, 0.7, 0.5), (outer, 1.0, 0.4)], names, imp, (0.1,) * 3
    )
    alone, _ = analysis_and_spec(
        (h, w), [*pair, (nothing, 0.7, 0.5), (nothing, 1.0, 0.4)], names, imp, (0.1,) * 3
    )
    res, ref = transparency(both, spec), transparency(alone, spec)
    assert res.per_structure["outer"]["perceived_transparency"] is None  # uniform: no TAP
    assert res.per_structure["band"]["perceived_transparency"] == pytest.approx(0.35, abs=1e-6)
    assert ref.E_t > 0.01
    assert res.E_t == pytest.approx(ref.E_t, abs=1e-9)
    left_out = [r for r in res.regions if not r["counted"]]
    assert {tuple(r["layers"]) for r in left_out} == {(), ("outer",), ("inner", "outer")}


# -- Fig. 9 on neghip: the outer layer's alpha_t falls with its saturation (D2, D5) ---------------
def with_saturation(color, fraction):
    hue, _, value = colorsys.rgb_to_hsv(*color)
    return tuple(float(c) for c in colorsys.hsv_to_rgb(hue, fraction, value))


@pytest.mark.shared_data
@pytest.mark.slow
@pytest.mark.parametrize("cache", [True, False])
def test_neghip_outer_layer_transparency_falls_with_saturation(shared_data, cache):
    """Fig. 9: at 100/75/50/25 % saturation of 'diffuse lobes' (hue and value kept) the E_t
    measure's alpha_t of that outer layer falls with the saturation, as the TAP does."""
    vol = load_volume(shared_data / "neghip.nhdr")
    spec = load_spec(REPO / "state_files" / "neghip.json")
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=128, height=128)
    outer = "diffuse lobes"
    alphas, taps = [], []
    for pct in (100, 75, 50, 25):
        s = dataclasses.replace(
            spec,
            structures=tuple(
                dataclasses.replace(x, colour=with_saturation(x.colour, pct / 100))
                if x.name == outer
                else x
                for x in spec.structures
            ),
        )
        a = analyze(vol, s, cam, build_cache=cache)
        alphas.append(transparency(a, s).per_structure[outer]["perceived_transparency"])
        if cache:
            taps.append(covered_transmittance(a, s, outer).alpha)
    assert all(a is not None for a in alphas)
    assert all(x > y for x, y in itertools.pairwise(alphas)), alphas
    assert alphas[0] - alphas[-1] > 0.05, alphas
    if cache:
        assert all(x > y for x, y in itertools.pairwise(taps)), taps
