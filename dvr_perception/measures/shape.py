r"""Shape deviation of a rendering: structural curvature versus image variation (Sec. 4.2).

* The **structural shape** ``v_s`` of a pixel is the analysis ``curvature`` image: the
  visibility-weighted ``|H|`` (mean curvature) of the boundary samples along the ray.
* The **image variation** ``v_i`` is the gradient magnitude of the *log* luminance,
  ``log(Y + Y_0)`` with ``Y`` the linear CIE Y of the rendering composited over the background
  and ``Y_0 = DARK_LUMINANCE`` (0.01 of white): the local Weber contrast, the variation a
  viewer perceives.  Scaling every colour leaves it unchanged where the image is well above
  ``Y_0`` and lowers it where the image sinks toward black, so darkening alone never makes the
  image look more like the shape (decision D9: with the linear luminance, colours x 0.1 left
  white highlights carrying all the variation and lowered ``E_s``).

**One meaning at every image size (D9).**  Both images are read at a fixed scale relative to
the image, not per pixel: the gradient is a derivative of Gaussian (the paper's Sobel
operator, smoothed) with ``sigma = max(H, W) / REFERENCE_SIZE`` pixels (2 px at 96 px, the
optimiser's sampling size; 10.7 px at 512), in log-luminance per ``sigma``, and the curvature
image is smoothed with the same Gaussian over the non-empty pixels only (a Gaussian mean of
their values, so empty rays do not dilute the silhouette).  A smooth shading ramp and a
silhouette edge then keep their proportions at every size (with per-pixel Sobel the ramps'
share fell with the size and ``E_s`` fell from 0.81 to 0.47 on the phantom between 32 and 128
px).  Each pixel's curvature is one ray's point sample: a scale of 1 px at 96 px left the
sampling noise of fine structures in the normalisation (bonsai's ``E_s`` spread 19 % over
96..512 px), 2 px brings it to 6 %.  Below 24 px ``sigma`` stays 0.5 px.

Both are normalised to [0, 1] by a **scale that smoothing keeps**: divided by
``MEAN_FACTOR`` (3) times their mean over the non-empty pixels and clipped to 1.  A
Gaussian keeps a mean but not an upper percentile: each pixel is one ray's point sample, and
at 96 px the point samples of fine structures (noise, hair, thin vessels) are smoothed over
few pixels, at 512 px over many, so a 99th-percentile "robust maximum" shrank with the size
(cthead's ``E_s`` rose from 0.34 at 48 px to 0.56 at 128 px on the paper's Fig. 8 view);
with the mean it moves by 1-3 % over 96..512 px (``benchmarks/size_invariance.py``).  With
``percentile`` set, the ``percentile``-th percentile is the scale instead (the earlier
robust maximum).  If the scale is 0 the normalised image is 0.  Gradient magnitudes below
``GRADIENT_FLOOR`` (1e-5 per ``sigma``) are float rounding of a flat image and count as 0;
otherwise a flat image would be normalised by its rounding noise.  Likewise curvatures below
``CURVATURE_FLOOR`` (1e-6 per world unit, a radius of a million units) are the float rounding
of a flat boundary and count as 0: without this floor, an image of flat structures would have
its rounding noise normalised to 1 and score ``delta_s`` near 1 everywhere.  The per-pixel
deviation (Eq. 3)

.. math:: \delta_s = 1 - \exp(-(v_s - v_i)^2 / s)

is high where the image hides a curved structure or shows variation over a flat one.  The
default steepness ``s = 0.05`` makes a normalised difference of 0.1 cost 0.18, of 0.3 cost
0.83 and of 0.5 cost 0.99: small mismatches (noise, shading falloff) are tolerated while a
clearly wrong shape cue counts almost fully.  ``E_s`` (Eq. 4) is the mean of ``delta_s`` over the
non-empty pixels (accumulated opacity above 1e-3), a share of the image that does not depend
on its pixel count.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from dvr_perception._numba import kernels
from dvr_perception.errors import DVRInputError
from dvr_perception.measures.results import (
    ShapeResult,
    _accumulated,
    _curvature,
    _image_luminance,
    _names,
    _remembered,
)
from dvr_perception.rays._results import engine_made

__all__ = ["shape"]

#: Pixels with accumulated opacity above this show some structure.
NONEMPTY_OPACITY = 1e-3
#: Gradient magnitudes of the log luminance (per sigma) below this are rounding noise: 0.
GRADIENT_FLOOR = 1e-5
#: Image size (longer side, pixels) at which the image variation is read at 1 px (D9).
REFERENCE_SIZE = 48
#: ``Y_0`` of the log luminance ``log(Y + Y_0)``: contrast far below it is not seen.
DARK_LUMINANCE = 0.01
#: Both images are divided by this times their mean over the non-empty pixels (D9).
MEAN_FACTOR = 3.0
#: Curvatures (1/world units) below this are rounding noise of flat boundaries and set to 0.
CURVATURE_FLOOR = 1e-6


def _robust_normalise(
    values: np.ndarray, nonempty: np.ndarray, percentile, what: str, notes: list[str]
) -> np.ndarray:
    """``values / scale`` clipped to [0, 1]; 0 if the scale is 0.

    The scale is ``MEAN_FACTOR`` times the mean over ``nonempty``, or the ``percentile``-th
    percentile there when ``percentile`` is not ``None``.
    """
    if not nonempty.any():
        return np.zeros_like(values)
    if percentile is None:
        scale = MEAN_FACTOR * float(values[nonempty].mean())
        which = f"{MEAN_FACTOR:g} x the mean"
    else:
        scale = float(np.percentile(values[nonempty], percentile))
        which = f"the {percentile:g}th percentile"
    if scale <= 0.0:
        if values[nonempty].max() > 0:
            notes.append(
                f"{what}: {which} over non-empty pixels is 0 although some pixels vary; "
                "normalised to 0"
            )
        return np.zeros_like(values)
    return np.clip(values / scale, 0.0, 1.0)


def _smoothed_over(values: np.ndarray, mask: np.ndarray, sigma: float, filtered=None):
    """Gaussian mean of ``values`` over the pixels of ``mask`` (0 outside it).

    ``filtered``: the two Gaussians ``(num, den)`` already made (:func:`_filters`).
    """
    if filtered is None:
        weight = mask.astype(np.float64)
        num = ndimage.gaussian_filter(values * weight, sigma, mode="nearest")
        den = ndimage.gaussian_filter(weight, sigma, mode="nearest")
    else:
        num, den = filtered
    out = np.divide(num, den, out=np.zeros_like(num), where=mask & (den > 0))
    out[out < CURVATURE_FLOOR] = 0.0
    return out


@functools.lru_cache(maxsize=16)
def _weights(sigma: float, order: int) -> np.ndarray:
    """Return scipy's correlation weights of ``gaussian_filter1d(sigma, order)`` (read-only).

    The filter's response to a unit impulse, read backwards: exactly the weights scipy
    correlates with (truncated at 4 sigma), whatever its version computes them as.
    """
    r = int(4.0 * float(sigma) + 0.5)
    impulse = np.zeros(4 * r + 3)
    c = 2 * r + 1
    impulse[c] = 1.0
    out = ndimage.gaussian_filter1d(impulse, sigma, order=order, mode="constant")
    w = np.ascontiguousarray(out[c - r : c + r + 1][::-1])
    w.flags.writeable = False
    return w


def _filters(values: np.ndarray, mask: np.ndarray, log_y: np.ndarray, sigma: float):
    """Return the shape measure's Gaussians: ``(num, den)`` and ``|grad log_y|``.

    ``(num, den)`` as :func:`_smoothed_over` makes them, the gradient magnitude as
    ``scipy.ndimage.gaussian_gradient_magnitude``, to the bit: :func:`_windowed_filters`
    pasted into whole images.
    """
    window, inner, outside = _windowed_filters(values, mask, log_y, sigma)
    out = tuple(np.full(mask.shape, f) for f in outside)
    for o, i in zip(out, inner, strict=True):
        o[window] = i
    return out


def _filter_window(mask: np.ndarray, log_y: np.ndarray, sigma: float):
    """Return ``(window, size, constant)``: where :func:`_windowed_filters` filters.

    The window is the bounding box of the pixels where anything varies (the pixels of
    ``mask``, and those whose ``log_y`` differs from ``constant``, a corner's value, usually
    the background's; of the corners, the one giving the smallest window), widened by the
    filters' radius plus one; ``size`` is its pixel count (0: nothing varies).
    """
    radius = int(4.0 * float(sigma) + 0.5)  # scipy's kernel radius (truncate=4)
    best = None
    for flat in dict.fromkeys(log_y[[0, 0, -1, -1], [0, -1, 0, -1]].tolist()):
        window = _window(mask | (log_y != flat), radius)
        size = (window[0].stop - window[0].start) * (window[1].stop - window[1].start)
        if best is None or size < best[1]:
            best = (window, size, flat)
    return best


def _windowed_filters(values, mask, log_y, sigma, window=None):
    """:func:`_filters` on a window: ``(window, (num, den, grad) there, outside values)``.

    Only the window of :func:`_filter_window` (or ``window = (window, size, constant)``
    found already; ``values`` may then be given on the window only) is filtered: that gives
    the same bits as filtering the whole image.  Inside the window every sum reads the same
    values in the same order (the window's edge rows and columns hold the constant that lies
    beyond them, so clamping at the window's edge repeats what the image holds there), and
    outside it every output is the filters' response to the constant image (three floats,
    made once on one pixel).  A rendering covering a third of the image is filtered on about
    half of it.
    """
    window, size, flat = _filter_window(mask, log_y, sigma) if window is None else window
    one = (np.zeros((1, 1)), np.zeros((1, 1), bool), np.full((1, 1), flat, np.float64))
    outside = tuple(float(f[0, 0]) for f in _filtered(*one, sigma))
    if size == 0:
        return window, tuple(np.empty((0, 0)) for _ in range(3)), outside
    if values.shape == mask.shape:
        values = values[window]
    return window, _filtered(values, mask[window], log_y[window], sigma), outside


def _window(varying: np.ndarray, radius: int) -> tuple[slice, slice]:
    """Bounding box of ``varying`` widened by ``radius + 1`` (empty without such pixels)."""
    rows = np.flatnonzero(varying.any(axis=1))
    if rows.size == 0:
        return slice(0, 0), slice(0, 0)
    cols = np.flatnonzero(varying.any(axis=0))
    height, width = varying.shape
    return (
        slice(max(int(rows[0]) - radius - 1, 0), min(int(rows[-1]) + radius + 2, height)),
        slice(max(int(cols[0]) - radius - 1, 0), min(int(cols[-1]) + radius + 2, width)),
    )


def _filtered(values: np.ndarray, mask: np.ndarray, log_y: np.ndarray, sigma: float):
    """:func:`_filters` on the whole of the images given.

    With numba the eight one-dimensional passes run as two parallel kernel calls
    (:func:`~._kernels.correlate_columns`, then :func:`~._kernels.correlate_rows`) and give
    scipy's bits; without, scipy's filters.
    """
    weight = mask.astype(np.float64)
    nk = kernels("dvr_perception.measures._kernels")
    if nk is None:
        num = ndimage.gaussian_filter(values * weight, sigma, mode="nearest")
        den = ndimage.gaussian_filter(weight, sigma, mode="nearest")
        grad = ndimage.gaussian_gradient_magnitude(log_y, sigma, mode="nearest")
        return num, den, grad
    g0, g1 = _weights(sigma, 0), _weights(sigma, 1)
    stack = np.stack([values * weight, weight, log_y, log_y])
    # scipy filters axis 0 first, then axis 1: the derivative of the gradient's first
    # component along axis 0, of its second along axis 1
    first = np.empty_like(stack)
    nk.correlate_columns(stack, np.stack([g0, g0, g1, g0]), np.array([1, 1, -1, 1]), first)
    num, den, d0, d1 = second = np.empty_like(first)
    nk.correlate_rows(first, np.stack([g0, g0, g0, g1]), np.array([1, 1, 1, -1]), second)
    d0 *= d0
    d1 *= d1
    d0 += d1
    return num, den, np.sqrt(d0, out=d0)


def image_scale(shape) -> float:
    """Gaussian ``sigma`` (pixels) of the image variation for an image of ``shape`` (D9).

    Examples
    --------
    >>> image_scale((96, 96)), image_scale((512, 384)), image_scale((16, 16))
    (2.0, 10.666666666666666, 0.5)
    """
    return max(max(shape) / REFERENCE_SIZE, 0.5)


def _check_options(steepness, percentile) -> tuple[float, float | None]:
    try:
        s = float(steepness)
        p = None if percentile is None else float(percentile)
    except (TypeError, ValueError):
        raise DVRInputError(
            f"steepness and percentile must be numbers, got {steepness!r}, {percentile!r}"
        ) from None
    if not (np.isfinite(s) and s > 0):
        raise DVRInputError(f"steepness must be a positive finite number, got {steepness!r}")
    if p is not None and not 0.0 < p <= 100.0:
        raise DVRInputError(f"percentile must lie in (0, 100], got {percentile!r}")
    return s, p


def shape(
    analysis, spec=None, *, steepness: float = 0.05, percentile: float | None = None
) -> ShapeResult:
    """Shape deviation ``E_s`` of a rendering (Eq. 3-4).

    Parameters
    ----------
    analysis : RayAnalysis
        Ray analysis with ``curvature`` and ``accumulated`` (H, W) and ``rgba`` (H, W, 4,
        premultiplied) or ``image`` (H, W, 3).
    spec : StructureSpec, optional
        With a spec, the luminance is that of ``rgba`` over ``spec.background`` (and its names
        must match ``analysis.names``); without, that of ``analysis.image``.
    steepness : float, optional
        ``s`` of Eq. 3 (default 0.05; see the module docstring).
    percentile : float, optional
        Normalise both images by this percentile in (0, 100] over the non-empty pixels (a
        robust maximum) instead of ``MEAN_FACTOR`` times their mean (default ``None``: the
        mean, which keeps ``E_s`` the same at every image size, D9).

    Returns
    -------
    ShapeResult
        ``E_s``, the per-pixel ``deviation`` (0 on empty pixels), the normalised ``v_s`` and
        ``v_i``, the ``nonempty`` mask and ``notes``.

    Raises
    ------
    DVRInputError
        If a field is missing, non-finite or misshapen, ``curvature`` is negative, or an option
        is out of range.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> flat = SimpleNamespace(curvature=np.ones((4, 4)), accumulated=np.ones((4, 4)),
    ...                        image=np.full((4, 4, 3), 0.5))  # curved structure, flat image
    >>> round(shape(flat, percentile=99.0).E_s, 6)  # v_s 1, v_i 0: 1 - exp(-1 / 0.05)
    1.0
    >>> round(shape(flat).E_s, 4)  # by default v_s = 1/3 (3 x the mean): 1 - exp(-1 / 0.45)
    0.8916
    """
    s, p = _check_options(steepness, percentile)
    if engine_made(analysis):  # the optimiser's terms and measures read one rendering: once
        # what the spec gives the measure: the names (checked) and the background (luminance)
        seen = None if spec is None else (tuple(spec.names), tuple(spec.background))
        try:
            key = ("shape", seen, s, p)
            hash(key)
        except (TypeError, AttributeError):  # not a spec that can be a key: nothing kept
            return _shape(analysis, spec, s, p)
        return _remembered(analysis, key, lambda: _frozen(_shape(analysis, spec, s, p)))
    return _shape(analysis, spec, s, p)


def _frozen(result: ShapeResult) -> ShapeResult:
    """Return ``result`` with its arrays read-only (every caller that asks again gets it)."""
    for arr in (result.deviation, result.v_s, result.v_i, result.nonempty):
        arr.flags.writeable = False
    return result


def _shape(analysis, spec, s: float, p: float | None) -> ShapeResult:
    """:func:`shape` after its options are checked (``s`` the steepness, ``p`` the percentile)."""
    accumulated = _accumulated(analysis)
    curvature = _curvature(analysis, accumulated.shape)
    if getattr(analysis, "names", None) is not None and spec is not None:
        _names(analysis, spec, len(analysis.names))
    y, notes = _image_luminance(analysis, spec, accumulated.shape)

    nonempty = accumulated > NONEMPTY_OPACITY
    sigma = image_scale(accumulated.shape)
    log_y = np.log(np.asarray(y, np.float64) + DARK_LUMINANCE)
    # every pixel that is not empty lies in the filters' window, and outside it the images
    # hold constants: the rest is worked out on the window (the same numbers, in the same
    # order, as on the whole image) and pasted into images of those constants
    found = _filter_window(nonempty, log_y, sigma)
    window = found[0]
    curvature = curvature[window]
    curvature = np.where(curvature < CURVATURE_FLOOR, 0.0, curvature)
    _, (num, den, gradient), outside = _windowed_filters(curvature, nonempty, log_y, sigma, found)
    inside = nonempty[window]
    curvature = _smoothed_over(curvature, inside, sigma, (num, den))
    v_s = _robust_normalise(curvature, inside, p, "curvature", notes)
    # outside the window: no non-empty pixel (curvature 0) and the constant image's gradient
    gradient = np.append(gradient.ravel(), outside[2])  # the last: every pixel outside
    gradient *= sigma
    gradient[gradient < GRADIENT_FLOOR] = 0.0
    v_i = _robust_normalise(gradient, np.append(inside.ravel(), False), p, "image gradient", notes)
    v_i, v_i_rest = v_i[:-1].reshape(inside.shape), v_i[-1]
    delta = np.where(inside, -np.expm1(-((v_s - v_i) ** 2) / s), 0.0)
    if inside.any():
        e_s = float(delta[inside].mean())
    else:
        e_s = 0.0
        notes.append("no pixel shows any structure (accumulated opacity <= 1e-3); E_s = 0")
    images = []
    for value, rest in ((delta, 0.0), (v_s, 0.0), (v_i, v_i_rest)):
        image = np.full(nonempty.shape, rest, np.float32)
        image[window] = value
        images.append(image)
    deviation, v_s, v_i = images
    return ShapeResult(
        E_s=e_s,
        deviation=deviation,
        v_s=v_s,
        v_i=v_i,
        nonempty=nonempty,
        notes=tuple(notes),
    )
