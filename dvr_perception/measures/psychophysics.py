r"""Perceived transmittance of a transparent layer: Metelli, TAP, their blend and Eq. 9.

Equation numbers refer to the paper (Sec. 4.3).  All inputs are **luminances** (see
:mod:`dvr_perception.measures.luminance`); a transmittance ``alpha`` is the fraction of light a
layer lets through, so the perceived opacity is ``1 - alpha``.  Undetermined values (a
vanishing denominator) are returned as NaN, as documented per function; callers exclude them.
Transmittances are *not* clipped to [0, 1]: a value outside means the luminances do not
support a transparency percept, which is information the caller may want.

Robust luminance range (Sec. 4.3.1, with sigma the population standard deviation)::

    I_min = max(0, mu - 2 sigma),    I_max = min(i_max, mu + 2 sigma)

Why the Michelson ratio (Eq. 7) of a uniform overlay is ``alpha mu_A / (alpha mu_A + (1 -
alpha) t)`` -- the closed form the tests check.  Let the overlay region be
``P = alpha A + (1 - alpha) t`` pixel by pixel, with a uniform layer luminance ``t``.  Then

* ``mu_P = alpha mu_A + (1 - alpha) t``  (the mean is affine), and
* ``sigma_P = alpha sigma_A``  (the constant ``t`` does not spread the samples).

Without clipping, ``I_max - I_min = 4 sigma`` and ``I_max + I_min = 2 mu``, so the Michelson
contrast is ``C = 2 sigma / mu`` and

    C(P) / C(A) = (2 alpha sigma_A / mu_P) / (2 sigma_A / mu_A) = alpha mu_A / mu_P
                = alpha mu_A / (alpha mu_A + (1 - alpha) t).

The range ratio (Eq. 6) is ``4 alpha sigma_A / 4 sigma_A = alpha`` exactly.  Michelson hence
equals ``alpha`` only for a black layer (``t = 0``); a bright layer raises the mean and lowers
the perceived transmittance, as Singh & Anderson's data show.  With clipping (``mu +- 2
sigma`` outside ``[0, i_max]``) both forms are approximations.
"""

from __future__ import annotations

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.measures.luminance import _finite_array

__all__ = [
    "blended_transmittance",
    "calibrate",
    "generalized_metelli",
    "luminance_range",
    "metelli_transmittance",
    "tap_transmittance",
]

_CONTRASTS = ("michelson", "range")


def _scalar_or_array(out: np.ndarray):
    return out[()] if out.ndim == 0 else out


def _positive(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name} must be a positive number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise DVRInputError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _nan_ok_array(x, name: str) -> np.ndarray:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name} must be an array of real numbers, got {x!r:.80}") from None
    if np.any(np.isinf(arr)):
        raise DVRInputError(f"{name} must not contain inf (NaN marks an undetermined value)")
    return arr


def _ratio(num: np.ndarray, den: np.ndarray, eps: float) -> np.ndarray:
    """``num / den`` where ``|den| >= eps``, NaN elsewhere (no warnings)."""
    num, den = np.broadcast_arrays(num, den)
    out = np.full(num.shape, np.nan)
    np.divide(num, den, out=out, where=np.abs(den) >= eps)
    return out


def _broadcast(arrays: dict[str, np.ndarray]) -> None:
    try:
        np.broadcast_shapes(*(a.shape for a in arrays.values()))
    except ValueError:
        shapes = ", ".join(f"{k} {a.shape}" for k, a in arrays.items())
        raise DVRInputError(
            f"{', '.join(arrays)} must have broadcastable shapes, got {shapes}"
        ) from None


def metelli_transmittance(p, q, a, b, *, eps: float = 1e-6):
    """Metelli's transmittance of a layer over a bipartite background, Eq. 5.

    With the layer (transmittance ``alpha``, luminance ``t``) over backgrounds ``a`` and ``b``,
    Talbot's law gives ``p = alpha a + (1 - alpha) t`` and ``q = alpha b + (1 - alpha) t``,
    hence ``alpha = (p - q) / (a - b)``.

    Parameters
    ----------
    p, q : float or array_like
        Luminance of the layer seen over background ``A`` and over background ``B``.
    a, b : float or array_like
        Luminance of the plain backgrounds ``A`` and ``B``.  All four broadcast together.
    eps : float, optional
        Where ``|a - b| < eps`` the transmittance is undetermined and the result is NaN.

    Returns
    -------
    alpha : float or ndarray
        ``(p - q) / (a - b)``, NaN where undetermined; not clipped to [0, 1].

    Raises
    ------
    DVRInputError
        If an input is not finite numeric, shapes do not broadcast, or ``eps`` is not positive.

    Examples
    --------
    >>> alpha, t, a, b = 0.4, 0.9, 0.8, 0.2
    >>> p, q = alpha * a + (1 - alpha) * t, alpha * b + (1 - alpha) * t
    >>> round(float(metelli_transmittance(p, q, a, b)), 9)
    0.4
    >>> bool(np.isnan(metelli_transmittance(0.5, 0.4, 0.3, 0.3)))
    True
    """
    eps = _positive(eps, "eps")
    arrs = {n: _finite_array(v, n) for n, v in zip("pqab", (p, q, a, b), strict=True)}
    _broadcast(arrs)
    return _scalar_or_array(_ratio(arrs["p"] - arrs["q"], arrs["a"] - arrs["b"], eps))


def generalized_metelli(i_all, i_layer, i_rest, i_empty, *, eps: float = 1e-6):
    r"""Transmittance of one of several overlapping layers, the generalised Metelli Eq. 9.

    For an overlapping layer set :math:`L` and one of its layers :math:`L_i`,

    .. math:: \alpha_{L_i} = (I_{L} - I_{L_i}) / (I_{L - L_i} - I_{\emptyset})

    where :math:`I_X` is the luminance of the sub-region in which **exactly** the layer set
    :math:`X` is present (enclosing layers ignored: :math:`I_\emptyset` is the view without
    any of the overlapping layers, which may still show an enclosing layer).

    Exactness under over-compositing, where a layer of transmittance ``alpha_k`` and luminance
    ``t_k`` maps the luminance behind it to ``alpha_k I_behind + (1 - alpha_k) t_k``:

    * **any depth order** when all layers of :math:`L` have the same luminance ``t``
      (including pure filters, ``t = 0``): then :math:`I_X = t + (I_\emptyset - t)
      \prod_{k \in X} \alpha_k` does not depend on the order;
    * **any layer luminances** when :math:`L_i` lies in front of every other layer of
      :math:`L`: Eq. 9 is then Eq. 5 with :math:`L - L_i` as background ``A``.

    Otherwise it is an approximation.  For a layer with front layers :math:`F` and at least one
    layer behind it, the exact value follows by passing ``i_layer`` :math:`= I_{F \cup L_i}`
    and ``i_empty`` :math:`= I_F` (the front layers act as a common medium).

    Parameters
    ----------
    i_all : float or array_like
        :math:`I_{L}`: luminance where all layers of :math:`L` overlap.
    i_layer : float or array_like
        :math:`I_{L_i}`: luminance where :math:`L_i` alone is present.
    i_rest : float or array_like
        :math:`I_{L - L_i}`: luminance where all layers but :math:`L_i` are present.
    i_empty : float or array_like
        :math:`I_{\emptyset}`: luminance where none of the layers of :math:`L` is present.
    eps : float, optional
        Where ``|i_rest - i_empty| < eps`` the result is NaN (undetermined).

    Returns
    -------
    alpha : float or ndarray
        Transmittance of :math:`L_i`; NaN where undetermined; not clipped.

    Raises
    ------
    DVRInputError
        If an input is not finite numeric, shapes do not broadcast, or ``eps`` is not positive.

    Examples
    --------
    >>> bg, a0, t0, a1, t1 = 0.2, 0.5, 0.9, 0.7, 0.4  # layer 0 in front of layer 1
    >>> over = lambda alpha, t, behind: alpha * behind + (1 - alpha) * t
    >>> i_all, i_0, i_1 = over(a0, t0, over(a1, t1, bg)), over(a0, t0, bg), over(a1, t1, bg)
    >>> round(float(generalized_metelli(i_all, i_0, i_1, bg)), 9)
    0.5
    """
    eps = _positive(eps, "eps")
    names = ("i_all", "i_layer", "i_rest", "i_empty")
    arrs = {
        n: _finite_array(v, n)
        for n, v in zip(names, (i_all, i_layer, i_rest, i_empty), strict=True)
    }
    _broadcast(arrs)
    num = arrs["i_all"] - arrs["i_layer"]
    return _scalar_or_array(_ratio(num, arrs["i_rest"] - arrs["i_empty"], eps))


def _samples(x, name: str, i_max: float) -> np.ndarray:
    arr = _finite_array(x, name).ravel()
    if arr.size == 0:
        raise DVRInputError(f"{name} must contain at least one luminance sample, got none")
    slack = 1e-6 * i_max
    if arr.min() < -slack or arr.max() > i_max + slack:
        raise DVRInputError(
            f"{name} must hold luminances in [0, i_max={i_max:g}], "
            f"got range [{arr.min():.6g}, {arr.max():.6g}]"
        )
    return np.clip(arr, 0.0, i_max)


def _robust_range(samples: np.ndarray, i_max: float) -> tuple[float, float]:
    mu, sigma = float(samples.mean()), float(samples.std())
    return max(0.0, mu - 2.0 * sigma), min(i_max, mu + 2.0 * sigma)


def luminance_range(samples, *, i_max: float = 1.0) -> tuple[float, float]:
    """Robust luminance range ``(I_min, I_max)`` of a region (Sec. 4.3.1).

    ``I_min = max(0, mu - 2 sigma)`` and ``I_max = min(i_max, mu + 2 sigma)`` with ``mu`` the
    mean and ``sigma`` the population standard deviation of the samples.

    Parameters
    ----------
    samples : array_like
        Luminance samples of the region (any shape, flattened), in ``[0, i_max]``.
    i_max : float, optional
        Largest displayable luminance (default 1).

    Returns
    -------
    (I_min, I_max) : tuple of float

    Raises
    ------
    DVRInputError
        If there are no samples, a sample is not finite or lies outside ``[0, i_max]``.

    Examples
    --------
    >>> lo, hi = luminance_range([0.4, 0.6])  # mu 0.5, sigma 0.1
    >>> round(lo, 9), round(hi, 9)
    (0.3, 0.7)
    >>> luminance_range([0.0, 1.0])  # clipped to [0, 1]
    (0.0, 1.0)
    """
    i_max = _positive(i_max, "i_max")
    return _robust_range(_samples(samples, "samples", i_max), i_max)


def _contrast(lo: float, hi: float, kind: str) -> float:
    if kind == "range":
        return hi - lo
    return (hi - lo) / (hi + lo) if hi + lo > 0 else 0.0


def tap_transmittance(lum_P, lum_A, *, contrast: str = "michelson", i_max: float = 1.0) -> float:
    """Transmittance by the transmittance anchoring principle: contrast ratio, Eq. 6 / Eq. 7.

    ``alpha = C(P) / C(A)`` where ``P`` is the region seen through the layer and ``A`` the
    plain background region, and ``C`` is the robust luminance range ``I_max - I_min``
    (``contrast="range"``, Eq. 6) or the Michelson contrast ``(I_max - I_min) / (I_max +
    I_min)`` (``contrast="michelson"``, Eq. 7); see :func:`luminance_range`.  For a uniform
    layer, ``"range"`` recovers the physical transmittance and ``"michelson"`` gives
    ``alpha mu_A / (alpha mu_A + (1 - alpha) t)`` (derivation in the module docstring).

    Parameters
    ----------
    lum_P : array_like
        Luminance samples of the overlay region ``P`` (any shape, flattened), in ``[0, i_max]``.
    lum_A : array_like
        Luminance samples of the plain background region ``A``.
    contrast : {"michelson", "range"}, optional
        Contrast measure (default ``"michelson"``, Eq. 7).
    i_max : float, optional
        Largest displayable luminance (default 1).

    Returns
    -------
    alpha : float
        The contrast ratio; NaN when ``A`` has (almost) no contrast (``C(A) < 1e-6``, or
        ``1e-6 * i_max`` for ``"range"``).  Not clipped: > 1 means ``P`` has more contrast than
        ``A``.

    Raises
    ------
    DVRInputError
        If a sample set is empty, non-finite or outside ``[0, i_max]``, or ``contrast`` is not
        one of the two names.

    Examples
    --------
    >>> A = np.array([0.4, 0.6])
    >>> P = 0.5 * A + 0.5 * 0.5  # a 50 % layer of luminance 0.5
    >>> round(tap_transmittance(P, A, contrast="range"), 9)
    0.5
    >>> round(tap_transmittance(P, A), 9)  # michelson: 0.5 * 0.5 / (0.5 * 0.5 + 0.5 * 0.5)
    0.5
    """
    if contrast not in _CONTRASTS:
        raise DVRInputError(f"contrast must be 'michelson' or 'range', got {contrast!r}")
    i_max = _positive(i_max, "i_max")
    c_p = _contrast(*_robust_range(_samples(lum_P, "lum_P", i_max), i_max), contrast)
    c_a = _contrast(*_robust_range(_samples(lum_A, "lum_A", i_max), i_max), contrast)
    eps = 1e-6 * (i_max if contrast == "range" else 1.0)
    return float(c_p / c_a) if c_a >= eps else float("nan")


def blended_transmittance(alpha_met, alpha_tap, contrast, *, i_max: float = 1.0):
    """Blend of Metelli and TAP transmittances by the region's contrast, Eq. 8.

    ``alpha_t = h alpha_met + (1 - h) alpha_tap`` with ``h = 1 - C``, ``C`` the evaluated
    region's contrast of Eq. 7: the Michelson contrast ``(I_max - I_min) / (I_max + I_min)``
    of its robust luminance range (project decision D2; the paper writes ``h = (I_MAX -
    I_range) / I_MAX`` with Eq. 7 defining ``I_range`` as that contrast).  So homogeneous
    regions (``C`` near 0) trust Metelli and contrasted ones TAP.  A luminance range (the
    Eq. 6 reading) may be passed instead with ``i_max`` the largest luminance: ``h = 1 -
    contrast / i_max``.  Where one of the two transmittances is NaN (undetermined) the other is
    used; both NaN gives NaN.

    Parameters
    ----------
    alpha_met : float or array_like
        Metelli transmittance (Eq. 5 or 9); NaN allowed.
    alpha_tap : float or array_like
        TAP transmittance (Eq. 6 or 7); NaN allowed.
    contrast : float or array_like
        Contrast ``C`` of the evaluated region, in ``[0, i_max]``: its Michelson contrast
        (Eq. 7, in [0, 1], with the default ``i_max``) or its robust luminance range.
    i_max : float, optional
        Largest value of ``contrast`` (default 1, right for the Michelson contrast).

    Returns
    -------
    alpha_t : float or ndarray

    Raises
    ------
    DVRInputError
        If an input contains inf, ``contrast`` is NaN or outside ``[0, i_max]``, or shapes do
        not broadcast.

    Examples
    --------
    A region with robust range [0.3, 0.5] has Michelson contrast 0.2 / 0.8 = 0.25:

    >>> round(float(blended_transmittance(0.2, 0.6, 0.25)), 9)  # h = 0.75
    0.3
    >>> float(blended_transmittance(np.nan, 0.6, 0.25))
    0.6
    """
    i_max = _positive(i_max, "i_max")
    met = _nan_ok_array(alpha_met, "alpha_met")
    tap = _nan_ok_array(alpha_tap, "alpha_tap")
    c = _finite_array(contrast, "contrast")
    if np.any(c < 0) or np.any(c > i_max):
        raise DVRInputError(f"contrast must lie in [0, i_max={i_max:g}], got {c.tolist()!r:.80}")
    _broadcast({"alpha_met": met, "alpha_tap": tap, "contrast": c})
    met, tap, c = np.broadcast_arrays(met, tap, c)
    h = 1.0 - c / i_max
    blend = h * np.where(np.isnan(met), 0.0, met) + (1.0 - h) * np.where(np.isnan(tap), 0.0, tap)
    out = np.where(np.isnan(met), tap, np.where(np.isnan(tap), met, blend))
    return _scalar_or_array(np.asarray(out, dtype=np.float64))


def _check_curve(curve) -> tuple[np.ndarray, np.ndarray]:
    try:
        knots = np.asarray(curve, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(
            f"curve must be a pair (x, y) of knot arrays, got {curve!r:.80}"
        ) from None
    if knots.ndim != 2 or knots.shape[0] != 2 or knots.shape[1] < 2:
        raise DVRInputError(
            f"curve must be a pair (x, y) of equally long knot arrays with at least 2 knots, "
            f"got shape {knots.shape}"
        )
    x, y = knots
    if not np.all(np.isfinite(knots)) or np.any(knots < 0) or np.any(knots > 1):
        raise DVRInputError("curve: knots x and y must be finite and lie in [0, 1]")
    if np.any(np.diff(x) <= 0):
        raise DVRInputError(f"curve: knot x values must be strictly increasing, got {x.tolist()}")
    if np.any(np.diff(y) < 0):
        raise DVRInputError(f"curve: knot y values must be non-decreasing, got {y.tolist()}")
    return x, y


def calibrate(alpha, curve=None):
    """Map transmittances through a monotone user-calibration curve (Sec. 6, Fig. 6c).

    The curve is piecewise linear through its knots (``np.interp``); outside the knots it is
    constant at the end values.  NaN (undetermined) stays NaN.

    Parameters
    ----------
    alpha : float or array_like
        Transmittances (NaN allowed).
    curve : pair of array_like (x, y), optional
        Knots with ``x`` strictly increasing, ``y`` non-decreasing, both in [0, 1], at least
        two.  ``None`` (default) is the identity: ``alpha`` is returned unchanged (as float).

    Returns
    -------
    calibrated : float or ndarray

    Raises
    ------
    DVRInputError
        If ``alpha`` contains inf or ``curve`` is malformed, unsorted, outside [0, 1] or
        decreasing.

    Examples
    --------
    >>> float(calibrate(0.25, curve=([0.0, 0.5, 1.0], [0.0, 0.7, 1.0])))
    0.35
    >>> float(calibrate(0.25))
    0.25
    """
    a = _nan_ok_array(alpha, "alpha")
    if curve is None:
        return _scalar_or_array(a.copy())
    x, y = _check_curve(curve)
    return _scalar_or_array(np.asarray(np.interp(a, x, y), dtype=np.float64))
