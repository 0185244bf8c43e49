"""The exported view: VTK's image with the legend and colour bar the page shows over it.

On screen the legend (each structure's colour, name and opacity) and the colour bar of the
value range are HTML over the rendering (:func:`dvr_perception.app.ui_tf.view_overlay`); the
exported PNG gets the same, drawn with Pillow in a panel to the right of the image, so the
rendering itself stays whole.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["PANEL_WIDTH", "save_png", "with_legend"]

#: Width in pixels of the legend panel added to the right of the image.
PANEL_WIDTH = 240
_PAD, _ROW, _SWATCH, _BAR = 10, 22, 14, 12
_BACKGROUND, _BAR_BACKGROUND, _TEXT = (33, 33, 33), (66, 66, 66), (255, 255, 255)


def _rgb(text: str) -> tuple[int, int, int]:
    s = str(text).lstrip("#")
    return tuple(int(s[i : i + 2], 16) for i in (0, 2, 4))


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: a fixed bitmap font
        return ImageFont.load_default()


def with_legend(image, *, rows, bar, value_range) -> np.ndarray:
    """Return ``image`` with a legend panel on its right, as the page shows it over the view.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W, 3)`` or ``(H, W, 4)`` uint8, the rendering.
    rows : list of dict
        One per structure: ``name``, ``color`` (``#rrggbb``) and ``opacity``.
    bar : list of dict
        The colour bar's stops (:func:`dvr_perception.app.tf_view.colour_bar_stops`):
        ``color`` over ``start`` to ``end`` percent of ``value_range``.
    value_range : (float, float)
        The values at the bar's ends.

    Returns
    -------
    numpy.ndarray
        ``(max(H, panel height), W + PANEL_WIDTH, 3)`` uint8: the image at the top left
        (black below it if the legend is taller), the panel on the right.

    Examples
    --------
    >>> img = np.zeros((50, 40, 3), np.uint8)
    >>> out = with_legend(img, rows=[{"name": "bone", "color": "#ff0000", "opacity": 0.5}],
    ...                   bar=[{"color": "#ff0000", "start": 50, "end": 100}],
    ...                   value_range=(0, 255))
    >>> out.shape[1] == 40 + PANEL_WIDTH, bool((out == (255, 0, 0)).all(axis=2).any())
    (True, True)
    """
    from PIL import Image, ImageDraw

    img = np.asarray(image)[..., :3].astype(np.uint8)
    h, w = img.shape[:2]
    need = 2 * _PAD + _ROW * (len(rows) + 1) + _BAR + _ROW
    out = Image.new("RGB", (w + PANEL_WIDTH, max(h, need)), (0, 0, 0))
    out.paste(Image.fromarray(np.ascontiguousarray(img)), (0, 0))
    draw = ImageDraw.Draw(out)
    draw.rectangle((w, 0, w + PANEL_WIDTH - 1, out.height - 1), fill=_BACKGROUND)
    font = _font(14)
    x0, x1, y = w + _PAD, w + PANEL_WIDTH - _PAD, _PAD
    draw.text((x0, y), "structure", fill=_TEXT, font=font)
    draw.text((x1, y), "opacity", fill=_TEXT, font=font, anchor="ra")
    y += _ROW
    for r in rows:
        draw.rectangle((x0, y, x0 + _SWATCH, y + _SWATCH), fill=_rgb(r["color"]), outline=_TEXT)
        draw.text((x0 + _SWATCH + 8, y), str(r["name"]), fill=_TEXT, font=font)
        draw.text((x1, y), f"{float(r['opacity']):.2f}", fill=_TEXT, font=font, anchor="ra")
        y += _ROW
    draw.rectangle((x0, y, x1, y + _BAR), fill=_BAR_BACKGROUND)
    span = x1 - x0
    for b in bar:
        a = x0 + span * float(b["start"]) / 100.0
        e = max(x0 + span * float(b["end"]) / 100.0, a + 1)
        draw.rectangle((round(a), y, round(e), y + _BAR), fill=_rgb(b["color"]))
    y += _BAR + 4
    lo, hi = (float(v) for v in value_range)
    draw.text((x0, y), f"{lo:g}", fill=_TEXT, font=font)
    draw.text(((x0 + x1) / 2, y), "value", fill=_TEXT, font=font, anchor="ma")
    draw.text((x1, y), f"{hi:g}", fill=_TEXT, font=font, anchor="ra")
    return np.asarray(out)


def save_png(image, path) -> Path:
    """Write ``image`` (uint8 RGB) as a PNG at ``path`` (a temporary file renamed: no partial)."""
    from PIL import Image

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
