"""The report's acceptance checks: small pure functions that return a check record.

Every check is a dict ``{"name", "passed", "detail", "values"}``; the report collects them in
``summary.json`` and :func:`all_passed` tells whether every one holds.  Nothing here knows the
experiments: each function judges the numbers it is given, so the logic is testable on its own
(e.g. that :func:`monotone` rejects a non-monotone series).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

__all__ = [
    "all_passed",
    "failed",
    "lowered",
    "lowered_or_declined",
    "monotone",
    "moves_toward",
    "share_distance",
]


def _record(name: str, passed: bool, detail: str, values: dict) -> dict:
    return {"name": name, "passed": bool(passed), "detail": detail, "values": values}


def _finite(values) -> bool:
    return all(v is not None and math.isfinite(float(v)) for v in values)


def monotone(
    name: str, xs: Sequence[float], ys: Sequence[float], *, increasing: bool, strict: bool = True
) -> dict:
    """Check that ``ys`` is (strictly) increasing or decreasing along increasing ``xs``.

    Examples
    --------
    >>> monotone("t", [25, 50, 75, 100], [0.1, 0.2, 0.3, 0.4], increasing=True)["passed"]
    True
    >>> monotone("t", [25, 50, 75, 100], [0.1, 0.3, 0.2, 0.4], increasing=True)["passed"]
    False
    """
    pairs = sorted(zip(xs, ys, strict=True), key=lambda p: p[0])
    sx = [float(p[0]) for p in pairs]
    sy = [None if p[1] is None else float(p[1]) for p in pairs]
    values = {"x": sx, "y": sy, "increasing": increasing, "strict": strict}
    word = "increasing" if increasing else "decreasing"
    if len(sy) < 2:
        return _record(name, False, "fewer than 2 points", values)
    if not _finite(sy):
        return _record(name, False, "a value is undetermined (None or not finite)", values)
    steps = [b - a for a, b in itertools.pairwise(sy)]
    sign = 1.0 if increasing else -1.0
    ok = all(sign * d > 0 for d in steps) if strict else all(sign * d >= 0 for d in steps)
    bad = [
        f"{sx[i]:g}->{sx[i + 1]:g}: {steps[i]:+.4f}"
        for i in range(len(steps))
        if not (sign * steps[i] > 0 if strict else sign * steps[i] >= 0)
    ]
    detail = f"{'strictly ' if strict else ''}{word} in x" + (
        "" if ok else f"; violated at {', '.join(bad)}"
    )
    return _record(name, ok, detail, values)


def lowered(name: str, before: float, after: float, *, margin: float = 0.0) -> dict:
    """Check ``after < before - margin`` (a strict decrease: "unchanged" does not pass).

    Examples
    --------
    >>> lowered("E_v", 0.5, 0.4)["passed"], lowered("E_v", 0.5, 0.5)["passed"]
    (True, False)
    """
    values = {"before": before, "after": after, "margin": margin}
    if not _finite([before, after]):
        return _record(name, False, "a value is not finite", values)
    ok = float(after) < float(before) - margin
    change = float(after) - float(before)
    rel = change / float(before) if float(before) else float("nan")
    return _record(name, ok, f"{before:.4f} -> {after:.4f} ({change:+.4f}, {rel:+.1%})", values)


def lowered_or_declined(name: str, before: float, after: float, changed: bool) -> dict:
    """Check a stage of the pipeline under decision D4's rule.

    Passes when the lead term fell (``after < before``), or when the stage kept no change
    (``changed`` False: it found no improving move, or its move was undone at the user's
    resolution, and said so) and the term is unchanged.  Fails when the term rose, or when
    the stage changed the rendering without lowering its lead term.

    Examples
    --------
    >>> lowered_or_declined("t", 0.5, 0.4, True)["passed"]
    True
    >>> lowered_or_declined("t", 0.5, 0.5, False)["passed"]
    True
    >>> lowered_or_declined("t", 0.5, 0.5, True)["passed"]
    False
    >>> lowered_or_declined("t", 0.5, 0.6, False)["passed"]
    False
    """
    rec = lowered(name, before, after)
    rec["values"]["changed"] = bool(changed)
    if rec["passed"] or not _finite([before, after]):
        return rec
    if not changed and float(after) == float(before):
        rec.update(passed=True, detail=rec["detail"] + "; the stage kept no change (D4)")
    return rec


def share_distance(shares: Sequence[float], target: Sequence[float]) -> float:
    """L1 distance between normalised ``shares`` and normalised ``target`` compositions.

    Examples
    --------
    >>> round(share_distance([0.9, 0.1], [0.2, 0.8]), 6)
    1.4
    """
    s, t = [float(v) for v in shares], [float(v) for v in target]
    ss, ts = sum(s), sum(t)
    if ss <= 0 or ts <= 0:
        return float("nan")
    return float(sum(abs(a / ss - b / ts) for a, b in zip(s, t, strict=True)))


def moves_toward(
    name: str, before: Sequence[float], after: Sequence[float], target: Sequence[float]
) -> dict:
    """Check that the visible-share composition moves strictly closer (L1) to ``target``.

    Examples
    --------
    >>> moves_toward("eq", [0.9, 0.1], [0.6, 0.4], [0.2, 0.8])["passed"]
    True
    >>> moves_toward("eq", [0.6, 0.4], [0.9, 0.1], [0.2, 0.8])["passed"]
    False
    """
    d0, d1 = share_distance(before, target), share_distance(after, target)
    values = {
        "before": [float(v) for v in before],
        "after": [float(v) for v in after],
        "target": [float(v) for v in target],
        "distance_before": d0,
        "distance_after": d1,
    }
    if not _finite([d0, d1]):
        return _record(name, False, "empty composition", values)
    return _record(
        name, d1 < d0, f"L1 distance to the target composition {d0:.4f} -> {d1:.4f}", values
    )


def failed(checks: Sequence[dict]) -> list[dict]:
    """Return the checks that did not pass."""
    return [c for c in checks if not c["passed"]]


def all_passed(checks: Sequence[dict]) -> bool:
    """Return True when there is at least one check and every check passed.

    Examples
    --------
    >>> all_passed([{"passed": True}]), all_passed([]), all_passed([{"passed": False}])
    (True, False, False)
    """
    return bool(checks) and all(c["passed"] for c in checks)
