"""Progress callbacks of the long steps (curvature volume, ray analysis).

A step takes ``progress``: ``None`` or a callable receiving a fraction in [0, 1].  The step
calls it from the calling thread at natural boundaries (slices, bricks, groups of ray tiles;
never inside a numba kernel) with non-decreasing fractions, at most about 100 times, the
first with 0.0 and the last with 1.0.  A callback that raises :class:`StopIteration` stops
the step: it raises :class:`~dvr_perception.errors.DVRCancelled` and returns nothing.

:class:`Reporter` does the bookkeeping: sub-steps report into their share of the range and
share one record of the last fraction sent, so nested steps (a bricked walk inside
:func:`~dvr_perception.rays.engine.analyze`) still send each fraction once.
"""

from __future__ import annotations

from dvr_perception.errors import DVRCancelled, DVRInputError

__all__ = ["STEP", "Reporter", "reporter"]

#: A fraction is sent only when it exceeds the last one sent by this much (or is the final 1.0).
STEP = 0.01


class Reporter:
    """Send a step's fractions to ``callback``, mapped onto ``[lo, hi]`` and thinned.

    Parameters
    ----------
    callback : callable or None
        Receives a float in [0, 1]; ``None`` makes every call a no-op.
    lo, hi : float
        The part of the callback's range this step covers.

    Examples
    --------
    >>> got = []
    >>> r = Reporter(got.append)
    >>> for i in range(1001):
    ...     r(i / 1000)
    >>> len(got) <= 101, got[0], got[-1]
    (True, 0.0, 1.0)
    >>> r.sub(0.0, 0.5)(0.5)  # a sub-step cannot move the bar back
    >>> got[-1]
    1.0
    """

    __slots__ = ("_callback", "_hi", "_last", "_lo")

    def __init__(self, callback, lo: float = 0.0, hi: float = 1.0, _last=None) -> None:
        self._callback = callback
        self._lo, self._hi = float(lo), float(hi)
        self._last = [-1.0] if _last is None else _last  # shared with the sub-steps

    def __bool__(self) -> bool:
        """Whether anyone listens (a step may skip preparing its reports otherwise)."""
        return self._callback is not None

    def __call__(self, fraction: float) -> None:
        """Report that ``fraction`` (clipped to [0, 1]) of this step is done."""
        if self._callback is None:
            return
        f = self._lo + (self._hi - self._lo) * min(max(float(fraction), 0.0), 1.0)
        last = self._last[0]
        if f < last + STEP and not (f >= 1.0 > last):
            return
        self._last[0] = f
        try:
            self._callback(f)
        except StopIteration as stop:
            why = str(stop.args[0]) if stop.args else "the callback raised StopIteration"
            raise DVRCancelled(f"progress: cancelled ({why})") from None

    def sub(self, lo: float, hi: float) -> Reporter:
        """Return the reporter of a sub-step covering ``[lo, hi]`` of this step."""
        span = self._hi - self._lo
        return Reporter(self._callback, self._lo + span * lo, self._lo + span * hi, self._last)


def reporter(progress, name: str = "progress") -> Reporter:
    """Return a :class:`Reporter` for a step's ``progress`` argument (checked).

    ``progress`` may be ``None``, a callable or a :class:`Reporter` (a step calling another
    passes its own).
    """
    if isinstance(progress, Reporter):
        return progress
    if progress is not None and not callable(progress):
        raise DVRInputError(
            f"{name}: expected a callable taking a fraction in [0, 1] (or None), "
            f"got {type(progress).__name__}"
        )
    return Reporter(progress)
