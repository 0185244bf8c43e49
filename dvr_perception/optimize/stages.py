"""The stages of the hierarchical optimisation (paper, Sec. 5) and their registry.

A stage owns a subset of the rendering parameters, maps them to an unbounded vector (a logit
of each bounded parameter, so the conjugate-gradient solver needs no bounds) and leads one term
of Eq. 12:

============  ===========================================================  =========
stage         parameters (bounds)                                          leads
============  ===========================================================  =========
``opacity``   rendering opacity per structure ([0.01, 1])                  ``E_v``
``lighting``  ambient, diffuse, specular ([0, 1]) and specular power       ``E_s``
              ([1, 128], log scale) per structure; light azimuth and
              elevation in camera coordinates ([-75, 75] degrees each)
``colour``    HSV saturation ([0, 1]) and value ([0.05, 1]) per            ``E_t``
              structure; hue too with ``allow_hue`` (periodic)
============  ===========================================================  =========

Inside a stage the solver minimises ``w_v E_v + w_s E_s + w_t E_t`` with the **lead** term's
weight multiplied by :attr:`Stage.boost` (3), so the stage pursues its own aspect first.  A
parameter set is **feasible** for the stage when, compared with the stage's start,

* the lead term has not risen,
* every other term with a non-zero weight has risen by at most :attr:`Stage.tolerance` (0.05
  absolute; the measures are region-based and jump by a few hundredths under small changes,
  so 0.02 blocked nearly every step on the phantom), and
* (``opacity`` only) the mean accumulated opacity over the non-empty rays (``coverage``) is at
  least its starting value, or ``opacity_floor`` when given: no winning by fading.

Infeasibility is a penalty inside the search and a hard rule for the kept result; in addition
:func:`~dvr_perception.optimize.optimize` keeps a stage's result only if the user-weighted ``E``
has not risen at the user's resolution (else it falls back to an earlier best point or undoes
the stage).  New stages
subclass :class:`Stage` and are added with :func:`register_stage`.
"""

from __future__ import annotations

import colorsys
import math

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.optimize._problem import TERMS, Params

__all__ = ["STAGES", "ColourStage", "LightingStage", "OpacityStage", "Stage", "register_stage"]

_MARGIN = 1e-3  # the logit box extends this fraction beyond the bounds (finite at the ends)
_ANGLE = 75.0


def _encode(p, lo, hi):
    span = hi - lo
    a, b = lo - _MARGIN * span, hi + _MARGIN * span
    u = (np.clip(np.asarray(p, float), lo, hi) - a) / (b - a)
    return np.log(u / (1.0 - u))


def _decode(x, lo, hi):
    span = hi - lo
    a, b = lo - _MARGIN * span, hi + _MARGIN * span
    return np.clip(a + (b - a) / (1.0 + np.exp(-np.asarray(x, float))), lo, hi)


class Stage:
    """Base class of a stage: encode/decode its parameters and judge feasibility.

    Subclasses set :attr:`name`, :attr:`lead` and implement :meth:`encode`, :meth:`decode`
    and :meth:`describe`.

    Parameters
    ----------
    allow_hue : bool
        Whether colour stages may change hue.
    opacity_floor : float or None
        Lowest allowed coverage for stages that change opacity (``None``: the starting value).
    """

    name = "stage"
    lead = "E_v"
    boost = 3.0
    tolerance = 0.05

    def __init__(self, *, allow_hue: bool = False, opacity_floor: float | None = None) -> None:
        self.allow_hue = bool(allow_hue)
        self.opacity_floor = opacity_floor

    def encode(self, params: Params, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
        """Return ``(x, groups, group_structures)`` for the stage's parameters.

        ``x`` is the unbounded vector, ``groups`` the group index of each entry and
        ``group_structures`` per group the structure index (``None`` for a global group).
        """
        raise NotImplementedError

    def decode(self, params: Params, x: np.ndarray, active: np.ndarray) -> Params:
        """Return ``params`` with this stage's parameters taken from ``x``."""
        raise NotImplementedError

    def describe(self, params: Params, names) -> dict:
        """Return the stage's parameters as a JSON-friendly dict."""
        raise NotImplementedError

    def weights(self, weights: np.ndarray) -> np.ndarray:
        """Term weights used inside the stage (the lead term boosted)."""
        w = np.array(weights, float)
        w[TERMS.index(self.lead)] *= self.boost
        return w

    def constraints(self, terms: dict, start: dict, weights: np.ndarray) -> np.ndarray:
        """Constraint values relative to ``start``; feasible where all are <= 0.

        ``lead - lead_start`` and, for every other term with a non-zero weight,
        ``term - term_start - tolerance``.
        """
        out = [terms[self.lead] - start[self.lead]]
        for w, t in zip(weights, TERMS, strict=True):
            if t != self.lead and w > 0:
                out.append(terms[t] - start[t] - self.tolerance)
        return np.array(out, float)

    def penalty(self, terms: dict, start: dict, weights: np.ndarray) -> float:
        """Sum of the constraint violations (0 = feasible)."""
        return float(np.maximum(self.constraints(terms, start, weights), 0.0).sum())


class OpacityStage(Stage):
    """Stage 1: per-structure rendering opacity in [0.01, 1]; leads the visibility ``E_v``."""

    name, lead = "opacity", "E_v"
    bounds = (0.01, 1.0)

    def encode(self, params, active):  # noqa: D102 (see Stage)
        idx = np.flatnonzero(active)
        return _encode(params.opacities[idx], *self.bounds), np.arange(idx.size), list(idx)

    def decode(self, params, x, active):  # noqa: D102
        ops = params.opacities.copy()
        ops[np.flatnonzero(active)] = _decode(x, *self.bounds)
        return params.replace(opacities=ops)

    def describe(self, params, names):  # noqa: D102
        return {"opacity": {n: float(o) for n, o in zip(names, params.opacities, strict=True)}}

    def constraints(self, terms, start, weights):
        """Return the base constraints plus ``floor - coverage`` (no winning by fading)."""
        floor = start["coverage"] if self.opacity_floor is None else self.opacity_floor
        return np.append(super().constraints(terms, start, weights), floor - terms["coverage"])


class LightingStage(Stage):
    """Stage 2: per-structure Phong material and the light direction; leads the shape ``E_s``."""

    name, lead = "lighting", "E_s"
    _lo = np.array([0.0, 0.0, 0.0, math.log(1.0)])
    _hi = np.array([1.0, 1.0, 1.0, math.log(128.0)])

    def encode(self, params, active):  # noqa: D102 (see Stage)
        idx = np.flatnonzero(active)
        mat = params.lighting[idx].copy()
        mat[:, 3] = np.log(np.clip(mat[:, 3], 1.0, 128.0))
        x_mat = _encode(mat, self._lo, self._hi).ravel()
        d = params.light
        angles = np.degrees([math.atan2(d[0], d[2]), math.asin(np.clip(d[1], -1.0, 1.0))])
        x = np.concatenate([x_mat, _encode(angles, -_ANGLE, _ANGLE)])
        groups = np.concatenate([np.repeat(np.arange(idx.size), 4), [idx.size, idx.size]])
        return x, groups, [*idx, None]

    def decode(self, params, x, active):  # noqa: D102
        idx = np.flatnonzero(active)
        mat = _decode(np.reshape(x[: 4 * idx.size], (idx.size, 4)), self._lo, self._hi)
        mat[:, 3] = np.exp(mat[:, 3])
        lighting = params.lighting.copy()
        lighting[idx] = mat
        az, el = np.radians(_decode(x[4 * idx.size :], -_ANGLE, _ANGLE))
        light = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        return params.replace(lighting=lighting, light=light)

    def describe(self, params, names):  # noqa: D102
        keys = ("ambient", "diffuse", "specular", "specular_power")
        return {
            "lighting": {
                n: dict(zip(keys, map(float, row), strict=True))
                for n, row in zip(names, params.lighting, strict=True)
            },
            "light_direction": [float(v) for v in params.light],
        }


class ColourStage(Stage):
    """Stage 3: per-structure HSV saturation and value (hue with ``allow_hue``); leads ``E_t``."""

    name, lead = "colour", "E_t"
    _lo = np.array([0.0, 0.05])
    _hi = np.array([1.0, 1.0])
    _HUE_SCALE = 2.0  # x = 2 * hue: a gradient step of 0.01 moves the hue by 0.005

    def _hsv(self, params, idx):
        return np.array([colorsys.rgb_to_hsv(*np.clip(params.colors[i], 0, 1)) for i in idx])

    def encode(self, params, active):  # noqa: D102 (see Stage)
        idx = np.flatnonzero(active)
        hsv = self._hsv(params, idx).reshape(idx.size, 3)
        parts = [_encode(hsv[:, 1:], self._lo, self._hi)]
        if self.allow_hue:
            parts.append(hsv[:, :1] * self._HUE_SCALE)
        x = np.concatenate(parts, axis=1)
        groups = np.repeat(np.arange(idx.size), x.shape[1])
        return x.ravel(), groups, list(idx)

    def decode(self, params, x, active):  # noqa: D102
        idx = np.flatnonzero(active)
        hsv = self._hsv(params, idx).reshape(idx.size, 3)
        x = np.reshape(x, (idx.size, 3 if self.allow_hue else 2))
        hsv[:, 1:] = _decode(x[:, :2], self._lo, self._hi)
        if self.allow_hue:
            hsv[:, 0] = np.mod(x[:, 2] / self._HUE_SCALE, 1.0)
        colors = params.colors.copy()
        for row, i in zip(hsv, idx, strict=True):
            colors[i] = np.clip(colorsys.hsv_to_rgb(*row), 0.0, 1.0)
        return params.replace(colors=colors)

    def describe(self, params, names):  # noqa: D102
        return {
            "color": {
                n: [float(c) for c in col] for n, col in zip(names, params.colors, strict=True)
            }
        }


#: name -> Stage subclass; :func:`~dvr_perception.optimize.optimize` looks stages up here.
STAGES: dict[str, type[Stage]] = {}


def register_stage(name: str, cls: type[Stage]) -> None:
    """Register (or replace) the stage class used for ``stages=(..., name, ...)``.

    Examples
    --------
    >>> class Fixed(OpacityStage):
    ...     boost = 1.0
    >>> register_stage("opacity-unboosted", Fixed)
    >>> STAGES["opacity-unboosted"].boost
    1.0
    >>> del STAGES["opacity-unboosted"]
    """
    if not isinstance(name, str) or not name:
        raise DVRInputError(f"name: expected a non-empty string, got {name!r}")
    if not (isinstance(cls, type) and issubclass(cls, Stage)):
        raise DVRInputError(f"cls: expected a subclass of Stage, got {cls!r}")
    STAGES[name] = cls


register_stage("opacity", OpacityStage)
register_stage("lighting", LightingStage)
register_stage("colour", ColourStage)
register_stage("color", ColourStage)
