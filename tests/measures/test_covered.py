"""Known answers of ``covered_transmittance``: a grey veil over two opaque blocks.

Unshaded labelled volume, camera down ``-z`` through voxel centres (helpers of
``test_rendered``): a veil (label 1, two voxels thick, in front) covers the right half of a
light block (luminance 0.3) and the left half of a dark one (0.1), so it *overlaps* them, and
the covered pixels are half light, half dark.  Through the veil each covered pixel is
``T * Y + c`` with ``c = grey * (1 - T)``; without it, ``Y``.  The blocks' robust range is
[0, 0.4] (mean 0.2, std 0.1), so Michelson's TAP ratio is ``0.2 T / (0.2 T + c)`` and the
range ratio is ``T``.
"""

import dataclasses

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import covered_transmittance, transparency
from dvr_perception.rays.engine import analyze
from dvr_perception.structures import Structure, StructureSpec
from dvr_perception.structures.spec import RenderSettings
from dvr_perception.volume import Volume
from tests.measures.test_rendered import parallel_camera, sample_opacity, samples_in


def veil_scene(grey, veil_opacity=0.5):
    labels = np.zeros((24, 32, 32), np.uint8)
    labels[8:14, 10:22, 8:16] = 2
    labels[8:14, 10:22, 16:24] = 3
    labels[18:20, 6:26, 12:20] = 1  # over x 12..15 of the light and 16..19 of the dark block
    vol = Volume(np.zeros(labels.shape, np.uint8), labels=labels)
    settings = RenderSettings(shade=False, sample_distance=1.0, opacity_unit_distance=4.0)
    spec = StructureSpec(
        (
            Structure("veil", veil_opacity, (grey, grey, grey), label=1),
            Structure("light", 1.0, (0.3, 0.3, 0.3), label=2),
            Structure("dark", 1.0, (0.1, 0.1, 0.1), label=3),
        ),
        rendering=settings,
    )
    return vol, spec, parallel_camera(vol)


def veil_transmittance(vol, cam, opacity=0.5):
    return (1.0 - sample_opacity(opacity)) ** samples_in(vol, cam, 18, 20, 16, 14)


@pytest.mark.parametrize("grey", [0.3, 0.6, 0.9])
def test_michelson_tap_of_a_veil_is_the_closed_form(grey):
    vol, spec, cam = veil_scene(grey)
    a = analyze(vol, spec, cam, build_cache=True)
    t = veil_transmittance(vol, cam)
    res = covered_transmittance(a, spec, "veil")
    assert res.reason is None
    assert res.pixels == 12 * 8  # rows 10..21, columns 12..19
    assert res.alpha == pytest.approx(0.2 * t / (0.2 * t + grey * (1.0 - t)), abs=0.02)
    relations = transparency(a, spec).relations
    assert relations[("veil", "light")]["kind"] == "overlap"


def test_range_contrast_recovers_the_physical_transmittance():
    vol, spec, cam = veil_scene(0.6)
    res = covered_transmittance(
        analyze(vol, spec, cam, build_cache=True), spec, "veil", contrast="range"
    )
    assert res.alpha == pytest.approx(veil_transmittance(vol, cam), abs=0.02)


def test_a_brighter_veil_reads_less_transparent():
    """The Fig. 9 direction: the same opacity, more luminance, lower Michelson TAP."""
    alphas = []
    for grey in (0.2, 0.5, 0.8):
        vol, spec, cam = veil_scene(grey)
        alphas.append(
            covered_transmittance(analyze(vol, spec, cam, build_cache=True), spec, "veil").alpha
        )
    assert alphas[0] > alphas[1] > alphas[2]


def test_a_layer_over_nothing_is_undetermined():
    vol, spec, cam = veil_scene(0.6)
    a = analyze(vol, spec, cam, build_cache=True)
    res = covered_transmittance(a, spec, "veil", threshold=0.999)  # no footprint at all
    assert np.isnan(res.alpha)
    assert res.pixels == 0
    assert "over another layer" in res.reason


def test_bad_input_is_one_clear_error():
    vol, spec, cam = veil_scene(0.6)
    a = analyze(vol, spec, cam, build_cache=True)
    with pytest.raises(DVRInputError, match="structure: expected one of"):
        covered_transmittance(a, spec, "skin")
    with pytest.raises(DVRInputError, match="contrast"):
        covered_transmittance(a, spec, "veil", contrast="weber")
    # without a cache an engine analysis is walked again; a copy the engine did not make
    # cannot be (it does not hold the volume)
    b = dataclasses.replace(analyze(vol, spec, cam, build_cache=False))
    with pytest.raises(DVRInputError, match="build_cache=True"):
        covered_transmittance(b, spec, "veil")
