"""A viewer's calibration curve: measured -> perceived transmittance (Sec. 6, Fig. 6(c)).

:func:`fit_calibration` fits a **monotone** (non-decreasing) curve to a viewer's ratings by
isotonic regression (the pool-adjacent-violators algorithm): the least-squares fit among all
non-decreasing sequences.  Ratings of equal measured values are averaged first.  The fitted
values at the distinct measured values become the knots of a piecewise-linear curve; by default
the curve is anchored at ``(0, 0)`` and ``(1, 1)`` (an opaque layer is seen as opaque, an absent
one as absent) so that it maps [0, 1] onto [0, 1].

A :class:`CalibrationCurve` is accepted wherever :func:`dvr_perception.measures.calibrate`
takes a ``curve`` (it converts to the ``(x, y)`` knot array).  The JSON file format is::

    {"version": 1, "x": [x0, x1, ...], "y": [y0, y1, ...]}

with ``x`` strictly increasing, ``y`` non-decreasing, all values in [0, 1], at least two knots.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dvr_perception._files import write_json
from dvr_perception.errors import DVRInputError
from dvr_perception.measures.psychophysics import calibrate

__all__ = ["CalibrationCurve", "fit_calibration", "load_calibration", "save_calibration"]

CALIBRATION_VERSION = 1


def _knot_problem(x, y) -> tuple[str, str] | None:
    """``(field, message)`` describing the first problem of knots ``x``, ``y``, or None."""
    for name, vals in (("x", x), ("y", y)):
        if len(vals) < 2:
            return name, f"must hold at least 2 knots, got {len(vals)}"
        for i, v in enumerate(vals):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                return f"{name}[{i}]", f"must be a finite number, got {v!r}"
            if not 0.0 <= v <= 1.0:
                return f"{name}[{i}]", f"must lie in [0, 1], got {v!r}"
    if len(x) != len(y):
        return "y", f"must have as many knots as x ({len(x)}), got {len(y)}"
    for i in range(1, len(x)):
        if not x[i] > x[i - 1]:
            return "x", f"must be strictly increasing, but x[{i}] = {x[i]} <= x[{i - 1}]"
        if y[i] < y[i - 1]:
            return "y", f"must be non-decreasing (monotone), but y[{i}] = {y[i]} < y[{i - 1}]"
    return None


@dataclass(frozen=True)
class CalibrationCurve:
    """Knots of a monotone piecewise-linear map from measured to perceived transmittance.

    Parameters
    ----------
    x : tuple of float
        Measured transmittances, strictly increasing, in [0, 1].
    y : tuple of float
        Perceived transmittances, non-decreasing, in [0, 1].

    Examples
    --------
    >>> curve = CalibrationCurve((0.0, 0.5, 1.0), (0.0, 0.7, 1.0))
    >>> float(curve(0.25))
    0.35
    >>> from dvr_perception.measures import calibrate
    >>> float(calibrate(0.25, curve))
    0.35
    """

    x: tuple[float, ...]
    y: tuple[float, ...]

    def __post_init__(self) -> None:
        try:
            x = tuple(float(v) for v in np.asarray(self.x, dtype=np.float64).ravel())
            y = tuple(float(v) for v in np.asarray(self.y, dtype=np.float64).ravel())
        except (TypeError, ValueError):
            raise DVRInputError(
                f"CalibrationCurve: x and y must be sequences of numbers, got {self.x!r:.60}, "
                f"{self.y!r:.60}"
            ) from None
        problem = _knot_problem(x, y)
        if problem is not None:
            raise DVRInputError(f"CalibrationCurve: {problem[0]} {problem[1]}")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)

    def __array__(self, dtype=None, copy=None):
        """Return the ``(2, n)`` knot array ``[x, y]`` (what :func:`~.measures.calibrate` reads)."""
        return np.array([self.x, self.y], dtype=dtype)

    def __iter__(self):
        """Unpack as ``x, y = curve``."""
        return iter((self.x, self.y))

    def __call__(self, alpha):
        """Calibrated transmittance(s) of ``alpha`` (see :func:`~.measures.calibrate`)."""
        return calibrate(alpha, self)


def _pava(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares non-decreasing fit of ``y`` (pool adjacent violators)."""
    means: list[float] = []
    weights: list[float] = []
    counts: list[int] = []
    for value, weight in zip(y.tolist(), w.tolist(), strict=True):
        means.append(value)
        weights.append(weight)
        counts.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            m2, w2, c2 = means.pop(), weights.pop(), counts.pop()
            total = weights[-1] + w2
            means[-1] = (means[-1] * weights[-1] + m2 * w2) / total
            weights[-1] = total
            counts[-1] += c2
    return np.repeat(means, counts)


def _unit_values(values, name: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name} must be numbers in [0, 1], got {values!r:.80}") from None
    if arr.ndim != 1 or arr.size == 0:
        raise DVRInputError(f"{name} must be a non-empty 1-D sequence, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any((arr < 0) | (arr > 1)):
        raise DVRInputError(f"{name} must contain only numbers in [0, 1]")
    return arr


def fit_calibration(measured, rated, *, anchor: bool = True) -> CalibrationCurve:
    """Fit a monotone calibration curve to a viewer's ratings (isotonic regression).

    Parameters
    ----------
    measured : array_like
        Measured transmittance of each rated stimulus (e.g. from
        :func:`~.stimuli.measured_transmittance`), in [0, 1].  Repeats are allowed.
    rated : array_like
        The transmittance the viewer perceived for each stimulus, in [0, 1]; same length.
    anchor : bool, optional
        Add the knots ``(0, 0)`` and ``(1, 1)`` where the data do not reach 0 or 1 (default),
        so that the curve maps [0, 1] onto [0, 1].  Without anchors the curve is constant
        beyond the measured extremes.

    Returns
    -------
    CalibrationCurve
        Knots at the distinct measured values (plus anchors), with the isotonic fit as ``y``.

    Raises
    ------
    DVRInputError
        If the inputs are not equally long sequences in [0, 1], or fewer than two knots result.

    Examples
    --------
    >>> curve = fit_calibration([0.2, 0.4, 0.6, 0.8], [0.3, 0.5, 0.4, 0.9])
    >>> curve.x
    (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
    >>> [round(v, 6) for v in curve.y]
    [0.0, 0.3, 0.45, 0.45, 0.9, 1.0]
    """
    m = _unit_values(measured, "measured")
    r = _unit_values(rated, "rated")
    if m.shape != r.shape:
        raise DVRInputError(
            f"measured and rated must have the same length, got {m.size} and {r.size}"
        )
    xs, inverse, counts = np.unique(m, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse.ravel(), weights=r, minlength=xs.size)
    fitted = np.clip(_pava(sums / counts, counts.astype(np.float64)), 0.0, 1.0)
    x, y = xs.tolist(), fitted.tolist()
    if anchor:
        if x[0] > 0.0:
            x, y = [0.0, *x], [0.0, *y]
        if x[-1] < 1.0:
            x, y = [*x, 1.0], [*y, 1.0]
    if len(x) < 2:
        raise DVRInputError(
            f"measured must hold at least two distinct values when anchor=False (got only {x[0]})"
        )
    return CalibrationCurve(tuple(x), tuple(y))


def save_calibration(curve, path) -> Path:
    """Write a calibration curve as JSON ``{"version": 1, "x": [...], "y": [...]}`` (atomically).

    Parameters
    ----------
    curve : CalibrationCurve or pair (x, y)
        The curve; a pair is validated as a :class:`CalibrationCurve`.
    path : str or os.PathLike
        Output file (its directory must exist).

    Returns
    -------
    pathlib.Path

    Examples
    --------
    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "me.calibration.json"
    >>> _ = save_calibration(CalibrationCurve((0, 1), (0, 0.8)), p)
    >>> load_calibration(p).y
    (0.0, 0.8)
    """
    if not isinstance(curve, CalibrationCurve):
        try:
            x, y = curve
        except (TypeError, ValueError):
            raise DVRInputError(
                f"curve must be a CalibrationCurve or a pair (x, y), got {type(curve).__name__}"
            ) from None
        curve = CalibrationCurve(x, y)
    doc = {"version": CALIBRATION_VERSION, "x": list(curve.x), "y": list(curve.y)}
    return write_json(path, doc)


def load_calibration(path) -> CalibrationCurve:
    """Read and validate a calibration JSON file written by :func:`save_calibration`.

    Parameters
    ----------
    path : str or os.PathLike
        The JSON file.

    Returns
    -------
    CalibrationCurve

    Raises
    ------
    DVRInputError
        Naming the file and the field, if the file is missing or not JSON, ``version`` is not
        1, or ``x``/``y`` are not equally long lists in [0, 1] with ``x`` strictly increasing
        and ``y`` non-decreasing.
    """
    p = Path(path)
    if not p.is_file():
        raise DVRInputError(f"calibration file {p}: not found")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DVRInputError(f"calibration file {p}: not valid JSON ({err})") from None
    if not isinstance(doc, dict):
        raise DVRInputError(f"calibration file {p}: top level must be a JSON object")
    version = doc.get("version")
    if isinstance(version, bool) or version != CALIBRATION_VERSION:
        raise DVRInputError(
            f"calibration file {p}: field 'version' must be {CALIBRATION_VERSION}, got {version!r}"
        )
    for key in ("x", "y"):
        if not isinstance(doc.get(key), list):
            raise DVRInputError(
                f"calibration file {p}: field '{key}' must be a list of numbers in [0, 1], "
                f"got {doc.get(key)!r:.80}"
            )
    problem = _knot_problem(doc["x"], doc["y"])
    if problem is not None:
        raise DVRInputError(f"calibration file {p}: field '{problem[0]}' {problem[1]}")
    return CalibrationCurve(tuple(doc["x"]), tuple(doc["y"]))
