"""The lens: page fractions to pixels (the handlers are driven by the browser tests)."""

from __future__ import annotations

import pytest

from dvr_perception.app.lens import lens_region
from dvr_perception.errors import DVRInputError


def test_lens_region_from_page_fractions():
    rect = {"shape": "rect", "x0": 0.75, "y0": 0.1, "x1": 0.25, "y1": 0.5}
    assert lens_region(rect, 200, 100) == ("rect", 50.0, 10.0, 150.0, 50.0)
    circle = {"shape": "circle", "x0": 0.5, "y0": 0.5, "r": 0.25}
    assert lens_region(circle, 200, 100) == ("circle", 100.0, 50.0, 50.0)
    for bad in (None, {"shape": "star"}, {"shape": "rect", "x0": "a"}):
        with pytest.raises(DVRInputError, match="lens"):
            lens_region(bad, 10, 10)
