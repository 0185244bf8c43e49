"""The lens of the adaptive refinement (paper, Sec. 6): region masks and per-structure targets.

A region is given at the user's image resolution as a boolean ``(H, W)`` mask, a rectangle
``("rect", x0, y0, x1, y1)`` or a circle ``("circle", cx, cy, r)`` in pixel coordinates (x
to the right, y down, row 0 at the top; pixel ``(col, row)`` spans ``[col, col + 1)`` with its
centre at ``col + 0.5``): the region holds the pixels whose centre lies inside the rectangle or
within ``r`` of ``(cx, cy)``.
The optimiser samples the mask at the pixel centres of its reduced-resolution camera.
"""

from __future__ import annotations

import math

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = ["parse_region", "parse_targets", "resample_mask"]

_TARGET_KEYS = ("visibility", "transparency")


def _numbers(values, what: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise DVRInputError(f"region: {what} needs numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise DVRInputError(f"region: {what} needs finite numbers, got {values!r}")
    return out


def parse_region(region, height: int, width: int) -> np.ndarray | None:
    """Return the region as a boolean ``(height, width)`` mask (``None`` for no region).

    Raises
    ------
    DVRInputError
        If the region is malformed, empty or entirely outside the image.

    Examples
    --------
    >>> int(parse_region(("rect", 1, 0, 3, 2), 4, 4).sum())
    4
    >>> int(parse_region(("circle", 1.5, 1.5, 1.0), 4, 4).sum())
    5
    """
    if region is None:
        return None
    if isinstance(region, tuple) and region and isinstance(region[0], str):
        kind, params = region[0], region[1:]
        rows = np.arange(height)[:, None] + 0.5
        cols = np.arange(width)[None, :] + 0.5
        if kind == "rect" and len(params) == 4:
            x0, y0, x1, y1 = _numbers(params, "('rect', x0, y0, x1, y1)")
            if not (x0 < x1 and y0 < y1):
                raise DVRInputError(f"region: rectangle needs x0 < x1 and y0 < y1, got {region}")
            mask = (cols > x0) & (cols < x1) & (rows > y0) & (rows < y1)
        elif kind == "circle" and len(params) == 3:
            cx, cy, r = _numbers(params, "('circle', cx, cy, r)")
            if r <= 0:
                raise DVRInputError(f"region: circle radius must be positive, got {r}")
            mask = (cols - cx) ** 2 + (rows - cy) ** 2 <= r * r
        else:
            raise DVRInputError(
                "region: expected a boolean (H, W) mask, ('rect', x0, y0, x1, y1) or "
                f"('circle', cx, cy, r), got {region!r}"
            )
        if not mask.any():
            raise DVRInputError(
                f"region: {region} covers no pixel of the {width} x {height} image (outside "
                "the image or smaller than a pixel)"
            )
        return mask
    try:
        mask = np.asarray(region)
    except (TypeError, ValueError):
        mask = np.zeros(0)
    if mask.dtype != bool or mask.shape != (height, width):
        raise DVRInputError(
            f"region: a mask must be a boolean array of shape ({height}, {width}) (the camera's "
            f"image), got dtype {mask.dtype} and shape {mask.shape}"
        )
    if not mask.any():
        raise DVRInputError("region: the mask is empty (no pixel selected)")
    return mask.copy()


def resample_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """Sample ``mask`` at the pixel centres of a ``height x width`` image of the same view.

    A region too small to contain any reduced pixel centre keeps the pixel nearest its centroid.
    """
    if mask.shape == (height, width):
        return mask.copy()
    h0, w0 = mask.shape
    rows = np.minimum(((np.arange(height) + 0.5) * h0 / height).astype(int), h0 - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w0 / width).astype(int), w0 - 1)
    out = mask[rows[:, None], cols[None, :]]
    if not out.any():
        ys, xs = np.nonzero(mask)
        r = min(int((ys.mean() + 0.5) * height / h0), height - 1)
        c = min(int((xs.mean() + 0.5) * width / w0), width - 1)
        out[r, c] = True
    return out


def parse_targets(targets, names) -> dict[str, dict[str, float]]:
    """Validate ``{structure: {"visibility": share, "transparency": alpha}}`` (values in [0, 1]).

    Examples
    --------
    >>> parse_targets({"a": {"visibility": 0.5}}, ("a", "b"))
    {'a': {'visibility': 0.5}}
    """
    if targets is None:
        return {}
    if not isinstance(targets, dict):
        raise DVRInputError(f"targets: expected a dict {{structure: {{...}}}}, got {targets!r}")
    out: dict[str, dict[str, float]] = {}
    for name, wanted in targets.items():
        if name not in names:
            raise DVRInputError(
                f"targets: unknown structure {name!r}; expected one of {list(names)}"
            )
        if not isinstance(wanted, dict) or not wanted:
            raise DVRInputError(
                f"targets[{name!r}]: expected a non-empty dict with keys {_TARGET_KEYS}"
            )
        entry = {}
        for key, value in wanted.items():
            if key not in _TARGET_KEYS:
                raise DVRInputError(
                    f"targets[{name!r}]: unknown key {key!r}; expected {_TARGET_KEYS}"
                )
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise DVRInputError(f"targets[{name!r}][{key!r}]: expected a number in [0, 1]")
            if not 0.0 <= float(value) <= 1.0:
                raise DVRInputError(
                    f"targets[{name!r}][{key!r}]: expected a number in [0, 1], got {value}"
                )
            entry[key] = float(value)
        out[name] = entry
    return out
