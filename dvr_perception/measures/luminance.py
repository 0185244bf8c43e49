"""Luminance of rendered images, the input of the transparency measures (paper, Sec. 4.3).

Convention fixed by the project: the renderer's RGB is treated as **linear light** and the
luminance is CIE Y with the Rec. 709 / sRGB primaries,

    Y = 0.2126 R + 0.7152 G + 0.0722 B,

so that luminance is linear in the colours being composited and Metelli's equations (Eq. 5, 9)
hold on it exactly.  An RGBA image from the engine is **premultiplied** (its RGB already carries
the accumulated opacity); :func:`composite_luminance` puts it over a background colour first.
"""

from __future__ import annotations

import warnings

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning

__all__ = ["LUMA_WEIGHTS", "composite_luminance", "luminance"]

#: CIE Y weights of linear R, G, B (Rec. 709 primaries, D65 white).
LUMA_WEIGHTS = (0.2126, 0.7152, 0.0722)

_PREMULTIPLIED_SLACK = 1e-6


def _finite_array(x, name: str) -> np.ndarray:
    """``x`` as a float64 array, or :class:`DVRInputError` naming ``name``."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name} must be an array of real numbers, got {x!r:.80}") from None
    if not np.all(np.isfinite(arr)):
        raise DVRInputError(f"{name} must contain only finite numbers (found NaN or inf)")
    return arr


def _colour_array(x, name: str, channels: int) -> np.ndarray:
    arr = _finite_array(x, name)
    if arr.ndim < 1 or arr.shape[-1] != channels:
        hint = (
            "; use composite_luminance for RGBA" if channels == 3 and arr.shape[-1:] == (4,) else ""
        )
        raise DVRInputError(
            f"{name} must have {channels} channels in its last axis, got shape {arr.shape}{hint}"
        )
    return arr


def luminance(rgb) -> np.ndarray:
    """Linear-light CIE Y of an already-composited RGB image.

    Parameters
    ----------
    rgb : array_like, shape (..., 3)
        Linear RGB values (usually in [0, 1]), e.g. an image of shape ``(H, W, 3)``.

    Returns
    -------
    Y : ndarray of float64, shape (...)
        ``0.2126 R + 0.7152 G + 0.0722 B``.

    Raises
    ------
    DVRInputError
        If ``rgb`` is not numeric and finite or its last axis is not of length 3.

    Examples
    --------
    >>> float(luminance([1.0, 1.0, 1.0]))
    1.0
    >>> luminance([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]]).round(4)
    array([[0.7152, 0.2126]])
    """
    arr = _colour_array(rgb, "rgb", 3)
    return arr @ np.asarray(LUMA_WEIGHTS)


def composite_luminance(rgba_premultiplied, *, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Luminance of a premultiplied RGBA image composited over a uniform background colour.

    The composite is ``rgb + (1 - a) * background`` (the "over" operator); its luminance is
    ``Y(rgb) + (1 - a) * Y(background)``.

    Parameters
    ----------
    rgba_premultiplied : array_like, shape (..., 4)
        Premultiplied RGB and accumulated opacity ``a`` in [0, 1].
    background : sequence of 3 floats, optional
        Linear RGB of the background (default black, ``(0, 0, 0)``).

    Returns
    -------
    Y : ndarray of float64, shape (...)

    Raises
    ------
    DVRInputError
        If the image is not finite with 4 channels, an opacity lies outside [0, 1], or
        ``background`` is not three finite non-negative numbers.

    Warns
    -----
    DVRWarning
        If some colour channel exceeds its opacity, i.e. the image does not look premultiplied.

    Examples
    --------
    >>> px = [0.5, 0.5, 0.5, 0.5]  # grey at 50 % opacity, premultiplied
    >>> float(composite_luminance(px))
    0.5
    >>> float(composite_luminance(px, background=(1.0, 1.0, 1.0)))
    1.0
    """
    arr = _colour_array(rgba_premultiplied, "rgba_premultiplied", 4)
    bg = _finite_array(background, "background")
    if bg.shape != (3,) or np.any(bg < 0):
        raise DVRInputError(
            f"background must be three non-negative linear RGB values, got {np.ravel(bg).tolist()}"
        )
    alpha = arr[..., 3]
    if np.any(alpha < 0) or np.any(alpha > 1):
        raise DVRInputError(
            "rgba_premultiplied: opacity (channel 3) must lie in [0, 1], "
            f"got range [{alpha.min():.6g}, {alpha.max():.6g}]"
        )
    if np.any(arr[..., :3] > alpha[..., None] + _PREMULTIPLIED_SLACK):
        warnings.warn(
            "rgba_premultiplied: some colour channels exceed their opacity; "
            "is the image really premultiplied?",
            DVRWarning,
            stacklevel=2,
        )
    return _composite(arr, bg)


def _composite(arr: np.ndarray, bg: np.ndarray) -> np.ndarray:
    """:func:`composite_luminance` of checked float64 input (``bg``: three floats)."""
    weights = np.asarray(LUMA_WEIGHTS)
    return arr[..., :3] @ weights + (1.0 - arr[..., 3]) * float(bg @ weights)
