"""The stages of the hierarchical optimisation (paper, Sec. 5) and their registry.

A stage owns a subset of the rendering parameters, maps them to an unbounded vector (a logit
of each bounded parameter, so the conjugate-gradient solver needs no bounds) and leads one term
of Eq. 12:

============  ===========================================================  =========
stage         parameters (bounds)                                          leads
============  ===========================================================  =========
``opacity``   rendering opacity per structure ([0.01, 1]); SLSQP on exact    ``E_v``
              ``E_v``/coverage gradients (:mod:`~._exact`)
``lighting``  per structure: ambient ([0.05, 0.4]; diffuse = start         ``E_s``
              ambient+diffuse - ambient, in [0.4, 1]), specular
              ([0, 0.8]), specular power ([2, 96], log scale); one light
              direction within ~39 degrees of the headlight; brightness
              guard (see :class:`LightingStage`)
``colour``    HSV saturation (80 % of its start .. start + 0.2) and value  ``E_t``
              (>= 60 % of its start, >= 0.05) per structure; hue
              too with ``allow_hue`` (periodic)
============  ===========================================================  =========

Inside a stage the solver minimises ``w_v E_v + w_s E_s + w_t E_t`` with the **lead** term's
weight multiplied by :attr:`Stage.boost` (3), so the stage pursues its own aspect first.  A
parameter set is **feasible** for the stage when, compared with the stage's start,

* the lead term has not risen,
* every other term with a non-zero weight has risen by at most :attr:`Stage.tolerance` (0.05
  absolute; the measures are region-based and jump by a few hundredths under small changes,
  so 0.02 blocked nearly every step on the phantom) plus :attr:`Stage.trade` (1/2) of the
  lead term's decrease in the stage (the transparency measure jumps by 0.1-0.3 when the
  opacities of the engine change; the colour stage, which leads it, comes later), and
* the stage's :meth:`Stage.guards` hold: (``opacity``) the mean accumulated opacity over the
  non-empty rays (``coverage``) is at least ``coverage_keep`` times its start or
  ``opacity_floor``, when one is given (off by default: ``E_v`` needs no floor, D1), and
  the most important structure's share of the picture does not fall below its start or
  target (D6); (``lighting``, ``colour``) every structure's footprint luminance keeps >= 80 % of its
  value before the first of them: no winning by darkening.

Infeasibility is a penalty inside the search and a hard rule for the kept result; in addition
:func:`~dvr_perception.optimize.optimize` keeps the result only if, at the user's resolution,
the user-weighted ``E`` has not risen and every stage's guards hold (else it undoes the last
stages).  :attr:`Stage.fast` names the measures the gradient evaluations compute.  New stages
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
        Lowest allowed coverage for stages that change opacity (``None``: the starting
        value, see :meth:`OpacityStage.guards`).
    """

    name = "stage"
    lead = "E_v"
    boost = 3.0
    tolerance = 0.05
    trade = 0.5
    #: Measures computed by the finite-difference gradient evaluations (the others are taken
    #: as constant there); line-search and annealing points compute all three.
    fast = ("E_v", "E_s", "E_t")
    #: Whether :meth:`guards` are re-checked on the final result at the user's resolution,
    #: relative to the start of the whole optimisation (valid only for guards that no other
    #: stage affects, such as the opacity stage's coverage).
    recheck = False
    #: Whether the stage keeps the brightness guard (:meth:`brightness_guards`), its share.
    brightened = False
    BRIGHTNESS = 0.8
    reference = None

    def __init__(self, *, allow_hue: bool = False, opacity_floor: float | None = None) -> None:
        self.allow_hue = bool(allow_hue)
        self.opacity_floor = opacity_floor
        self.coverage_keep = None  # a fraction of the start replacing COVERAGE_KEEP

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
        ``term - term_start - tolerance - trade * gain`` with ``gain = lead_start - lead``
        (>= 0): another term may rise by :attr:`tolerance` (the measures' jitter) plus
        :attr:`trade` (1/2) of what the lead term gained, so every such rise is paid for
        at least twice over by the lead.
        """
        gain = max(0.0, float(start[self.lead] - terms[self.lead]))
        out = [terms[self.lead] - start[self.lead]]
        for w, t in zip(weights, TERMS, strict=True):
            if t != self.lead and w > 0:
                out.append(terms[t] - start[t] - self.tolerance - self.trade * gain)
        return np.array(out, float)

    def guards(self, terms: dict, start: dict, *, full: bool = False) -> np.ndarray:
        """Hard rules of the stage relative to ``start`` (feasible where all <= 0; none here)."""
        return np.zeros(0)

    def brightness_guards(self, terms: dict, start: dict) -> np.ndarray:
        """No winning by darkening: ``(cutoff - luminance) / reference`` per lit structure.

        ``cutoff = min(BRIGHTNESS * reference, start)`` with ``reference`` the footprint
        luminance in :attr:`reference` (the terms before the first brightness-guarded stage,
        set by :func:`~dvr_perception.optimize.optimize`; ``start`` when unset), so the
        lighting and colour stages together keep >= :attr:`BRIGHTNESS` of it.
        """
        ref = np.asarray((start if self.reference is None else self.reference)["luminance"])
        lum0 = np.asarray(start["luminance"], float)
        on = (ref > 1e-3) & (lum0 > 1e-3)
        cutoff = np.minimum(self.BRIGHTNESS * ref[on], lum0[on])
        return (cutoff - np.asarray(terms["luminance"], float)[on]) / ref[on]

    def penalty(self, terms: dict, start: dict, weights: np.ndarray) -> float:
        """Sum of the constraint violations (0 = feasible)."""
        return float(np.maximum(self.constraints(terms, start, weights), 0.0).sum())


class OpacityStage(Stage):
    """Stage 1: per-structure rendering opacity in [0.01, 1]; leads the visibility ``E_v``."""

    name, lead = "opacity", "E_v"
    bounds = (0.01, 1.0)
    fast = ("E_v", "E_s")  # cheap; E_t (transparency, expensive) checked at line-search points
    recheck = True
    exact = True  # solved by _solver._run_exact (exact E_v and coverage gradients)
    #: Fraction of the starting coverage kept by default: none (decision D1: fading raises
    #: ``E_v`` by itself, so no floor is needed); ``coverage_keep`` or ``opacity_floor`` set one.
    COVERAGE_KEEP = 0.0

    def encode(self, params, active):  # noqa: D102 (see Stage)
        idx = np.flatnonzero(active)
        return _encode(params.opacities[idx], *self.bounds), np.arange(idx.size), list(idx)

    def decode(self, params, x, active):  # noqa: D102
        ops = params.opacities.copy()
        ops[np.flatnonzero(active)] = _decode(x, *self.bounds)
        return params.replace(opacities=ops)

    def describe(self, params, names):  # noqa: D102
        return {"opacity": {n: float(o) for n, o in zip(names, params.opacities, strict=True)}}

    def floor(self, start: dict) -> float:
        """Return the lowest allowed coverage: ``opacity_floor``, else a fraction of the start.

        The fraction is ``coverage_keep`` (``optimize(..., coverage_keep=...)``) or
        :attr:`COVERAGE_KEEP` (0: no floor).
        """
        if self.opacity_floor is not None:
            return float(self.opacity_floor)
        keep = self.COVERAGE_KEEP if self.coverage_keep is None else self.coverage_keep
        return keep * float(start["coverage"])

    #: The most important structure (set by :func:`~dvr_perception.optimize.optimize`).
    protect: str | None = None
    #: Share of the picture a guarded structure may lose at the optimisation resolution, and
    #: at the user's (``full``: the re-check of the final result; a share found at 96 px moves
    #: by a few thousandths at 512 px).
    SHARE_SLACK = 1e-3
    SHARE_SLACK_FULL = 5e-3

    def share_bounds(self, start: dict) -> dict:
        """Bounds on shares of the picture (decision D6): ``{name: (low, high)}``.

        A structure whose share starts below its target share may only move toward the
        target: it keeps at least its start and ends no farther from the target than it
        started (``high = 2 target - start``).  The most important structure
        (:attr:`protect`) keeps its start or, when it starts above its target, the target.
        """
        shares, targets = start.get("visible_share", {}), start.get("target_share", {})
        out = {}
        for name, target in targets.items():
            share = shares.get(name, 0.0)
            if share < target:
                out[name] = (share, 2.0 * target - share)
            elif name == self.protect:
                out[name] = (target, np.inf)
        return out

    def guards(self, terms, start, *, full=False):
        """``floor - coverage`` (see :meth:`floor`) and the share bounds, two per structure.

        The share bounds (:meth:`share_bounds`, widened by :attr:`SHARE_SLACK`, or by
        :attr:`SHARE_SLACK_FULL` for the re-check at the user's resolution) keep every
        structure that has less of the picture than its target moving toward it, and what
        the user marked most important from falling below its start or target.
        """
        out = [self.floor(start) - terms["coverage"]]
        slack = self.SHARE_SLACK_FULL if full else self.SHARE_SLACK
        for name, (low, high) in self.share_bounds(start).items():
            share = terms["visible_share"][name]
            out += [low - share - slack, share - high - slack]
        return np.array(out)

    def constraints(self, terms, start, weights):
        """Return the base constraints plus :meth:`guards`."""
        return np.append(super().constraints(terms, start, weights), self.guards(terms, start))


class LightingStage(Stage):
    """Stage 2: per-structure Phong material and the light direction; leads the shape ``E_s``.

    The shape measure alone rewards flat or dark images (little shading contrast means
    little deviation from the curvature-predicted cues), so the stage's space is restricted
    to renderings that keep shading cues and brightness (an earlier free parameterisation
    raised ambient to 0.6-0.8 on the engine and drove a tumour's ambient to 0.02):

    * **ambient/diffuse split** (one parameter per structure): ``ambient`` in
      [:attr:`AMBIENT`] and ``diffuse = total - ambient`` clipped to [:attr:`DIFFUSE`], with
      ``total`` the structure's starting ``ambient + diffuse`` (clipped to [0.45, 1.4]), so
      the overall reflectance stays, only the amount of directional shading changes;
    * **specular** in [0, 0.8] and **specular power** in [2, 96] (log scale): the paper's
      shape cue "a large specular highlight (small specular exponent) on a large smooth
      surface" stays reachable, a mirror-like pin-point highlight (power 128) does not;
    * **one shared light direction** within a cone around the headlight: azimuth and elevation
      in camera coordinates in [-28, 28] degrees each (at most ~39 degrees off the view axis),
      so the lit side always faces the viewer;
    * a **brightness guard** (constraint, :meth:`Stage.brightness_guards`, shared with the
      colour stage): the mean luminance of each structure's footprint (``Problem``
      ``luminance``) must stay >= :attr:`BRIGHTNESS` (80 %) of its value before lighting.

    That is ``3 K + 2`` parameters (``4 K + 2`` before).  Lighting does not change
    visibility, so ``E_v`` is constant here; the gradient evaluations compute ``E_s`` only
    (:attr:`fast`), the transparency term is checked at the line-search points.
    """

    name, lead = "lighting", "E_s"
    fast = ("E_s",)
    brightened = True
    AMBIENT = (0.05, 0.4)
    DIFFUSE = (0.4, 1.0)
    ANGLE = 28.0
    _lo = np.array([AMBIENT[0], 0.0, math.log(2.0)])
    _hi = np.array([AMBIENT[1], 0.8, math.log(96.0)])

    def encode(self, params, active):  # noqa: D102 (see Stage)
        idx = np.flatnonzero(active)
        mat = params.lighting[idx][:, [0, 2, 3]].copy()
        mat[:, 2] = np.log(np.clip(mat[:, 2], 2.0, 96.0))
        x_mat = _encode(mat, self._lo, self._hi).ravel()
        d = params.light
        angles = np.degrees([math.atan2(d[0], d[2]), math.asin(np.clip(d[1], -1.0, 1.0))])
        x = np.concatenate([x_mat, _encode(angles, -self.ANGLE, self.ANGLE)])
        groups = np.concatenate([np.repeat(np.arange(idx.size), 3), [idx.size, idx.size]])
        return x, groups, [*idx, None]

    def decode(self, params, x, active):  # noqa: D102
        idx = np.flatnonzero(active)
        mat = _decode(np.reshape(x[: 3 * idx.size], (idx.size, 3)), self._lo, self._hi)
        total = np.clip(params.lighting[idx, 0] + params.lighting[idx, 1], 0.45, 1.4)
        lighting = params.lighting.copy()
        lighting[idx, 0] = mat[:, 0]
        lighting[idx, 1] = np.clip(total - mat[:, 0], *self.DIFFUSE)
        lighting[idx, 2] = mat[:, 1]
        lighting[idx, 3] = np.exp(mat[:, 2])
        az, el = np.radians(_decode(x[3 * idx.size :], -self.ANGLE, self.ANGLE))
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

    guards = Stage.brightness_guards

    def constraints(self, terms, start, weights):
        """Return the base constraints plus the brightness guard."""
        return np.append(super().constraints(terms, start, weights), self.guards(terms, start))


class ColourStage(Stage):
    """Stage 3: per-structure HSV saturation and value (hue with ``allow_hue``); leads ``E_t``.

    The hue is kept (unless ``allow_hue``), saturation stays in [``SATURATION_KEEP`` (80 %) of
    its start, its start + ``SATURATION_GAIN`` (0.2)] (at most 1) and value in [``VALUE_KEEP``
    (60 %) of its start (at least 0.05), 1], so structures keep their colour identity: with [0,
    1] and [0.05, 1] the engine's red inserts turned grey and lidc_chest's heart and aorta
    almost black (value 0.29; its footprint luminance, dominated by the layers in front, hardly
    changed), and with a saturation floor of 50 % the phantom's blue ventricle became near-white
    (washed out), without a ceiling the tooth's pale blue-white enamel (saturation 0.15) turned
    a strong blue (0.49).
    Plus the brightness guard of :class:`LightingStage`.
    """

    name, lead = "colour", "E_t"
    brightened = True
    guards = Stage.brightness_guards
    VALUE_KEEP = 0.6
    SATURATION_KEEP = 0.8
    SATURATION_GAIN = 0.2
    _HUE_SCALE = 2.0  # x = 2 * hue: a gradient step of 0.01 moves the hue by 0.005

    def _bounds(self, hsv0):
        """(lo, hi), shape (n, 2) each, of (saturation, value) given the starting HSV."""
        lo, hi = np.zeros((len(hsv0), 2)), np.ones((len(hsv0), 2))
        lo[:, 0] = np.minimum(self.SATURATION_KEEP * hsv0[:, 1], 0.95)
        lo[:, 1] = np.minimum(np.maximum(0.05, self.VALUE_KEEP * hsv0[:, 2]), 0.95)
        hi[:, 0] = np.minimum(hsv0[:, 1] + self.SATURATION_GAIN, 1.0)
        return lo, hi

    def _hsv(self, params, idx):
        return np.array([colorsys.rgb_to_hsv(*np.clip(params.colours[i], 0, 1)) for i in idx])

    def encode(self, params, active):  # noqa: D102 (see Stage)
        idx = np.flatnonzero(active)
        hsv = self._hsv(params, idx).reshape(idx.size, 3)
        parts = [_encode(hsv[:, 1:], *self._bounds(hsv))]
        if self.allow_hue:
            parts.append(hsv[:, :1] * self._HUE_SCALE)
        x = np.concatenate(parts, axis=1)
        groups = np.repeat(np.arange(idx.size), x.shape[1])
        return x.ravel(), groups, list(idx)

    def decode(self, params, x, active):  # noqa: D102
        idx = np.flatnonzero(active)
        hsv = self._hsv(params, idx).reshape(idx.size, 3)
        x = np.reshape(x, (idx.size, 3 if self.allow_hue else 2))
        hsv[:, 1:] = _decode(x[:, :2], *self._bounds(hsv))
        if self.allow_hue:
            hsv[:, 0] = np.mod(x[:, 2] / self._HUE_SCALE, 1.0)
        colours = params.colours.copy()
        for row, i in zip(hsv, idx, strict=True):
            colours[i] = np.clip(colorsys.hsv_to_rgb(*row), 0.0, 1.0)
        return params.replace(colours=colours)

    def constraints(self, terms, start, weights):
        """Return the base constraints plus the brightness guard."""
        return np.append(super().constraints(terms, start, weights), self.guards(terms, start))

    def describe(self, params, names):  # noqa: D102
        return {
            "color": {
                n: [float(c) for c in col] for n, col in zip(names, params.colours, strict=True)
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
