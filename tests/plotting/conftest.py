"""Scenes shared by the plotting tests: the 48^3 phantom at 96x96 with per-structure lighting."""

from __future__ import annotations

from dataclasses import replace

import pytest

from dvr_perception.rays.camera import Camera
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.structures.spec import Lighting

#: Distinct materials; structure i gets MATERIALS[i % n].
MATERIALS = (
    Lighting(0.1, 0.9, 0.6, 8.0),
    Lighting(0.3, 0.6, 0.1, 64.0),
    Lighting(0.15, 0.7, 0.8, 4.0),
    Lighting(0.4, 0.5, 0.5, 24.0),
    Lighting(0.05, 0.95, 0.0, 16.0),
    Lighting(0.25, 0.75, 0.3, 2.0),
)


def with_materials(spec, n: int):
    """``spec`` with structure ``i`` lit by ``MATERIALS[i % n]``."""
    structures = tuple(replace(s, lighting=MATERIALS[i % n]) for i, s in enumerate(spec.structures))
    return replace(spec, structures=structures)


@pytest.fixture(scope="session")
def phantom():
    """``(volume, spec with 4 distinct materials, camera 96x96)``."""
    vol, spec = make_phantom(size=48)
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, zoom=1.5, width=96, height=96)
    return vol, with_materials(spec, 4), cam
