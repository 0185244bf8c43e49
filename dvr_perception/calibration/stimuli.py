r"""Calibration stimuli: a transparent square of known transmittance over a background (Sec. 6).

The paper's calibration tool (Fig. 6(b)(c)) shows the viewer layers of known transparency and
records the transparency they perceive.  Each stimulus here is a linear-RGB grey image of size
``size x size``: a square layer (the central half of the image) of transmittance ``alpha`` and
luminance ``t`` composited over a background with the episcotister model (Talbot's law)

    p = alpha a + (1 - alpha) t

pixel by pixel, where ``a`` is the background luminance behind the pixel.  Two background kinds:

* ``"plain"``: a bipartite background, left half ``A`` of luminance ``a`` and right half ``B``
  of luminance ``b``; the layer straddles the boundary, covering ``P`` (over ``A``) and ``Q``
  (over ``B``).  Metelli's Eq. 5 recovers ``alpha`` exactly.
* ``"textured"``: a checkerboard-like texture of 8 x 8 cells whose luminances (``a`` or ``b``)
  are drawn at random from ``seed`` but balanced, so that the cells under the layer and the
  cells around it hold the two luminances half and half.  Both regions therefore have the same
  luminance mean and spread, and the TAP contrast ratio with the luminance range (Eq. 6)
  recovers ``alpha`` exactly; the Michelson ratio (Eq. 7) gives ``alpha mu / (alpha mu + (1 -
  alpha) t)`` instead (see :mod:`dvr_perception.measures.psychophysics`).

``"light"`` backgrounds use ``a, b = 0.8, 0.5`` under a dark layer (``t = 0.2``); ``"dark"``
backgrounds use ``a, b = 0.35, 0.15`` under a light layer (``t = 0.7``).  These keep the
texture's robust range ``mu +- 2 sigma`` inside [0, 1], so the TAP clipping never applies.
Grey pixels ``(L, L, L)`` have luminance exactly ``L`` (the Rec. 709 weights sum to 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.measures.luminance import luminance
from dvr_perception.measures.psychophysics import metelli_transmittance, tap_transmittance

__all__ = ["BACKGROUNDS", "Stimulus", "calibration_stimuli", "measured_transmittance"]

#: Background kind -> (luminance a, luminance b, default layer luminance t).
BACKGROUNDS = {"light": (0.8, 0.5, 0.2), "dark": (0.35, 0.15, 0.7)}
_TEXTURES = ("plain", "textured")
_CELLS = 8  # texture cells per side; the layer covers the central 4 x 4


@dataclass(frozen=True, eq=False)
class Stimulus:
    """One calibration image with the ground truth it was composited from.

    Attributes
    ----------
    image : numpy.ndarray
        ``(size, size, 3)`` float64 linear RGB in [0, 1], row 0 at the top.
    transmittance : float
        The layer's transmittance ``alpha`` (1 = fully transparent).
    layer_luminance : float
        The layer's luminance ``t``.
    background : str
        ``"light"`` or ``"dark"``.
    texture : str
        ``"plain"`` (bipartite) or ``"textured"``.
    masks : dict of str to numpy.ndarray
        Boolean ``(size, size)`` regions: ``"layer"`` (the square) and, for plain backgrounds,
        ``"A"``, ``"B"`` (background halves outside the layer), ``"P"``, ``"Q"`` (the layer over
        ``A`` and over ``B``); for textured backgrounds ``"A"`` (background around the layer)
        and ``"P"`` (the layer).
    """

    image: np.ndarray = field(repr=False)
    transmittance: float
    layer_luminance: float
    background: str
    texture: str
    masks: dict = field(repr=False)


def _check_choice(values, allowed, name: str) -> tuple[str, ...]:
    if isinstance(values, str):
        values = (values,)
    out = tuple(values)
    bad = [v for v in out if v not in allowed]
    if not out or bad:
        raise DVRInputError(
            f"{name} must be a non-empty sequence of {', '.join(map(repr, allowed))}, "
            f"got {values!r}"
        )
    return out


def _check_transmittances(values) -> np.ndarray:
    try:
        arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    except (TypeError, ValueError):
        raise DVRInputError(f"transmittances must be numbers in [0, 1], got {values!r}") from None
    if arr.ndim != 1 or arr.size == 0 or not np.all(np.isfinite(arr)):
        raise DVRInputError(f"transmittances must be a non-empty list of numbers, got {values!r}")
    if np.any((arr < 0) | (arr > 1)):
        raise DVRInputError(f"transmittances must lie in [0, 1], got {arr.tolist()}")
    return arr


def _layout(size: int) -> dict[str, np.ndarray]:
    rows, cols = np.indices((size, size))
    lo, hi = size // 4, 3 * size // 4
    layer = (rows >= lo) & (rows < hi) & (cols >= lo) & (cols < hi)
    left = cols < size // 2
    return {
        "layer": layer,
        "A": left & ~layer,
        "B": ~left & ~layer,
        "P": left & layer,
        "Q": ~left & layer,
    }


def _texture(size: int, a: float, b: float, rng: np.random.Generator) -> np.ndarray:
    """Balanced random two-luminance cell texture (half ``a``, half ``b`` inside and outside)."""
    inner = np.zeros((_CELLS, _CELLS), dtype=bool)
    inner[2:6, 2:6] = True
    cells = np.empty((_CELLS, _CELLS))
    for region in (inner, ~inner):
        n = int(region.sum())
        values = np.repeat([a, b], n // 2)
        cells[region] = rng.permutation(values)
    return np.kron(cells, np.ones((size // _CELLS, size // _CELLS)))


def calibration_stimuli(
    *,
    transmittances=(0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9),
    backgrounds=("light", "dark"),
    textures=("plain", "textured"),
    size: int = 128,
    seed: int = 0,
) -> list[Stimulus]:
    """Images of a transparent square of known transmittance for a user calibration test.

    Parameters
    ----------
    transmittances : sequence of float, optional
        Layer transmittances in [0, 1] (default 0.1, 0.2, ..., 0.9).
    backgrounds : sequence of {"light", "dark"}, optional
        Background brightness (see the module docstring for the luminances).
    textures : sequence of {"plain", "textured"}, optional
        Bipartite plain background or seeded balanced cell texture.
    size : int, optional
        Image side in pixels, a multiple of 8 and at least 16 (default 128).
    seed : int, optional
        Seed of the texture layout (default 0); the same seed gives the same images.

    Returns
    -------
    list of Stimulus
        One per (texture, background, transmittance), in that nesting order.

    Raises
    ------
    DVRInputError
        If an option is out of range or names an unknown kind.

    Examples
    --------
    >>> stims = calibration_stimuli(transmittances=(0.5,), size=16)
    >>> [(s.texture, s.background) for s in stims]
    [('plain', 'light'), ('plain', 'dark'), ('textured', 'light'), ('textured', 'dark')]
    >>> stims[0].image.shape
    (16, 16, 3)
    """
    alphas = _check_transmittances(transmittances)
    kinds = _check_choice(backgrounds, tuple(BACKGROUNDS), "backgrounds")
    texs = _check_choice(textures, _TEXTURES, "textures")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 16:
        raise DVRInputError(f"size must be an integer >= 16, got {size!r}")
    if size % _CELLS:
        raise DVRInputError(f"size must be a multiple of {_CELLS}, got {size}")
    try:
        rng = np.random.default_rng(seed)
    except (TypeError, ValueError):
        raise DVRInputError(f"seed must be a non-negative integer, got {seed!r}") from None
    layout = _layout(int(size))
    out = []
    for tex in texs:
        for kind in kinds:
            a, b, t = BACKGROUNDS[kind]
            for alpha in alphas:
                if tex == "plain":
                    bg = np.where(layout["A"] | layout["P"], a, b)
                    masks = {k: layout[k].copy() for k in ("layer", "A", "B", "P", "Q")}
                else:
                    bg = _texture(int(size), a, b, rng)
                    masks = {
                        "layer": layout["layer"].copy(),
                        "A": ~layout["layer"],
                        "P": layout["layer"].copy(),
                    }
                lum = np.where(layout["layer"], alpha * bg + (1.0 - alpha) * t, bg)
                image = np.repeat(lum[:, :, None], 3, axis=2)
                out.append(Stimulus(image, float(alpha), t, kind, tex, masks))
    return out


def measured_transmittance(stimulus: Stimulus, *, contrast: str = "range") -> float:
    """Transmittance of a stimulus' layer measured from its image alone.

    Plain (bipartite) backgrounds use Metelli's Eq. 5 on the mean luminances of ``P``, ``Q``,
    ``A`` and ``B``; textured backgrounds use the TAP contrast ratio ``C(P) / C(A)`` (Eq. 6 with
    ``contrast="range"``, Eq. 7 with ``"michelson"``).

    Parameters
    ----------
    stimulus : Stimulus
        A stimulus from :func:`calibration_stimuli`.
    contrast : {"range", "michelson"}, optional
        TAP contrast for textured stimuli.  ``"range"`` (default) recovers the composited
        transmittance; use ``"michelson"`` to calibrate against the Michelson-based measure
        (``transparency(..., contrast="michelson")``).

    Returns
    -------
    float

    Raises
    ------
    DVRInputError
        If ``stimulus`` is not a :class:`Stimulus` or ``contrast`` is unknown.

    Examples
    --------
    >>> s = calibration_stimuli(transmittances=(0.3,), textures=("plain",), size=16)[0]
    >>> round(measured_transmittance(s), 9)
    0.3
    """
    if not isinstance(stimulus, Stimulus):
        raise DVRInputError(f"stimulus must be a Stimulus, got {type(stimulus).__name__}")
    if contrast not in ("range", "michelson"):
        raise DVRInputError(f"contrast must be 'range' or 'michelson', got {contrast!r}")
    y = luminance(stimulus.image)
    m = stimulus.masks
    if stimulus.texture == "plain":
        p, q, a, b = (float(y[m[k]].mean()) for k in "PQAB")
        return float(metelli_transmittance(p, q, a, b))
    return tap_transmittance(y[m["P"]], y[m["A"]], contrast=contrast)
