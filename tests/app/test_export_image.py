"""The exported view PNG: the rendering with the legend and colour bar beside it."""

from __future__ import annotations

import numpy as np
from PIL import Image

from dvr_perception.app.export_image import PANEL_WIDTH, save_png, with_legend

ROWS = [
    {"name": "skin", "color": "#f0b48c", "opacity": 0.25},
    {"name": "bone", "color": "#2050ff", "opacity": 0.9},
]
BAR = [
    {"name": "skin", "color": "#f0b48c", "start": 10.0, "end": 30.0},
    {"name": "bone", "color": "#2050ff", "start": 60.0, "end": 95.0},
]


def _has(img: np.ndarray, hex_colour: str) -> int:
    rgb = [int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]
    return int((img == rgb).all(axis=2).sum())


def test_legend_panel_keeps_the_rendering_and_shows_every_swatch_and_the_bar(tmp_path):
    rng = np.random.default_rng(0)
    render = rng.integers(0, 256, size=(200, 120, 3), dtype=np.uint8)
    render[..., 2] = 0  # no pure swatch colour in the rendering itself
    out = with_legend(render, rows=ROWS, bar=BAR, value_range=(0, 255))
    assert out.shape == (200, 120 + PANEL_WIDTH, 3)
    assert np.array_equal(out[:, :120], render)  # the rendering is whole
    panel = out[:, 120:]
    for row in ROWS:
        # the swatch (14x14 inside its outline) and the bar's stretch of the colour
        assert _has(panel, row["color"]) > 13 * 13, row["name"]
    # the bar: bone's stop is wider than skin's (35 % against 20 % of the value range)
    assert _has(panel, "#2050ff") - 14 * 14 > _has(panel, "#f0b48c") - 14 * 14
    # light text on the dark panel: the names and numbers were drawn
    assert (panel.min(axis=2) > 200).sum() > 100
    path = save_png(out, tmp_path / "view.png")
    assert np.array_equal(np.asarray(Image.open(path).convert("RGB")), out)
    assert [p.name for p in tmp_path.iterdir()] == ["view.png"]  # no temporary file left


def test_a_legend_taller_than_the_image_extends_it():
    many = [{"name": f"s{k}", "color": "#00ff00", "opacity": 0.5} for k in range(12)]
    out = with_legend(np.full((40, 30, 3), 7, np.uint8), rows=many, bar=[], value_range=(0, 1))
    assert out.shape[0] > 40
    assert out.shape[1] == 30 + PANEL_WIDTH
    assert (out[:40, :30] == 7).all()
    assert (out[40:, :30] == 0).all()
