"""Image regression: the phantom through the PyVista plotter against stored baseline PNGs.

Regenerate the baselines (only after a deliberate change) with
``DVR_UPDATE_BASELINES=1 pytest tests/plotting/test_baselines.py``; they are never rewritten
otherwise, and a missing baseline fails.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dvr_perception._files import read_png, write_png
from dvr_perception.plotting import render_plotter
from dvr_perception.rays.vtk_reference import compare_images

BASELINES = Path(__file__).resolve().parent / "baselines"
UPDATE = os.environ.get("DVR_UPDATE_BASELINES", "") == "1"
SSIM_MIN = 0.99
MAD_MAX = 0.01


def matches_baseline(image, baseline) -> bool:
    """The regression tolerance: SSIM >= 0.99 and mean absolute difference <= 0.01."""
    scores = compare_images(image, baseline)
    return scores["ssim"] >= SSIM_MIN and scores["mean_abs_diff"] <= MAD_MAX


def _scene_spec(phantom, variant):
    vol, spec, cam = phantom
    if variant == "uniform":
        spec = replace(
            spec, structures=tuple(replace(s, lighting=type(s.lighting)()) for s in spec.structures)
        )
    return vol, spec, cam


def _baseline(name: str, image):
    path = BASELINES / f"{name}.png"
    if UPDATE:
        write_png(path, image)
    if not path.is_file():
        pytest.fail(f"baseline {path} missing; create it with DVR_UPDATE_BASELINES=1")
    return _read(path)


def _read(path):
    return np.asarray(read_png(path), dtype=np.float32) / 255.0


@pytest.mark.parametrize("variant", ["uniform", "per_structure"])
def test_phantom_matches_baseline(vtk_can_render, phantom, variant):
    vol, spec, cam = _scene_spec(phantom, variant)
    image = render_plotter(vol, spec, cam)
    baseline = _baseline(f"phantom_{variant}", image)
    assert baseline.shape == image.shape
    assert matches_baseline(image, baseline)


def test_changed_colour_fails_the_baseline(vtk_can_render, phantom):
    vol, spec, cam = _scene_spec(phantom, "per_structure")
    baseline = _read(BASELINES / "phantom_per_structure.png")
    structures = list(spec.structures)
    structures[3] = replace(structures[3], colour=(0.2, 1.0, 0.2))  # tumour: red -> green
    image = render_plotter(vol, replace(spec, structures=tuple(structures)), cam)
    assert not matches_baseline(image, baseline)
