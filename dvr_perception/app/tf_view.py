"""The transfer-function view's work: histogram, curves, handles, drags and view directions.

Everything the page's transfer-function editor shows is computed here from the volume and
the spec (numbers and SVG geometry only, no trame); the page only draws it and reports where
a handle was dropped, and :func:`dropped_edit` turns that into a range or opacity for
:meth:`~dvr_perception.app.session.Session.set_structure`.

The chart is an SVG ``viewBox`` of :data:`WIDTH` x :data:`HEIGHT` units; the plot area spans
``x`` from :data:`LEFT` to ``WIDTH - RIGHT`` (the volume's value range) and ``y`` from
:data:`TOP` (opacity 1) to ``HEIGHT - BOTTOM`` (opacity 0).  The page reports a drop as
fractions of the whole ``viewBox`` (``fx``, ``fy`` in 0..1).
"""

from __future__ import annotations

import math

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "AXES",
    "BINS",
    "axis_camera",
    "colour_bar_stops",
    "dropped_edit",
    "tf_chart",
    "value_histogram",
]

WIDTH, HEIGHT = 440.0, 170.0
LEFT, RIGHT, TOP, BOTTOM = 8.0, 8.0, 8.0, 30.0
#: The range-end handles sit this far above (low end) and below (high end) the axis, so the
#: ends of two touching ranges can both be grabbed.
END_OFFSET = 7.0
#: Histogram bins over the volume's value range.
BINS = 128
#: View-direction buttons: name -> direction from the volume's centre to the camera, view-up.
AXES = {
    "+X": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "-X": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "+Y": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "-Y": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "+Z": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "-Z": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
}


def _f(v: float) -> str:
    return f"{v:.1f}"


def value_histogram(volume, *, bins: int = BINS) -> dict:
    """Count the volume's values in ``bins`` equal bins over its value range.

    Returns
    -------
    dict
        ``{"lo", "hi", "counts"}``: the value range and the count per bin (ints).

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> h = value_histogram(Volume(np.arange(8, dtype=np.uint8).reshape(2, 2, 2)), bins=4)
    >>> h["lo"], h["hi"], h["counts"]
    (0.0, 7.0, [2, 2, 2, 2])
    """
    if int(bins) < 1:
        raise DVRInputError(f"histogram: bins must be at least 1, got {bins}")
    lo, hi = (float(v) for v in volume.scalar_range)
    if not hi > lo:
        hi = lo + 1.0
    counts = np.zeros(int(bins), np.int64)
    flat = volume.data.reshape(-1)
    step = 1 << 22  # slabs: no float copy of the whole volume
    for i in range(0, flat.size, step):
        counts += np.histogram(flat[i : i + step], bins=int(bins), range=(lo, hi))[0]
    return {"lo": lo, "hi": hi, "counts": [int(c) for c in counts]}


def _x(value: float, lo: float, hi: float) -> float:
    t = (float(value) - lo) / (hi - lo)
    return LEFT + (WIDTH - LEFT - RIGHT) * min(max(t, 0.0), 1.0)


def _y(opacity: float) -> float:
    return TOP + (HEIGHT - TOP - BOTTOM) * (1.0 - min(max(float(opacity), 0.0), 1.0))


def _trapezoid(s, lo: float, hi: float) -> list[tuple[float, float]]:
    """Chart points of a range structure's opacity trapezoid (see the spec's semantics)."""
    a, b = s.range
    e = float(s.edge) * (b - a)
    op = float(s.render_opacity)
    pts = ((a, 0.0), (a + e, op), (b - e, op), (b, 0.0))
    return [(_x(v, lo, hi), _y(o)) for v, o in pts]


def _points(pts) -> str:
    return " ".join(f"{_f(x)},{_f(y)}" for x, y in pts)


def tf_chart(histogram: dict, spec, *, before=None) -> dict:
    """Return the editor's geometry: log histogram, trapezoids, handles and ``before`` curves.

    Parameters
    ----------
    histogram : dict
        :func:`value_histogram` of the volume.
    spec : StructureSpec
        The transfer function shown.
    before : StructureSpec, optional
        The transfer function before the last optimisation (drawn dashed).

    Returns
    -------
    dict
        JSON-ready: ``width``, ``height``, ``bars`` (an SVG path of the log-scaled counts),
        ``ticks`` (value labels), ``structures`` (one row per range structure: ``index``,
        ``name``, ``color``, ``points``, handle positions ``x_lo``, ``x_hi``, ``x_mid``,
        ``y_top``, ``range``, ``opacity``) and ``before`` (``points`` and ``color`` per
        structure).

    Examples
    --------
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(0.0, 50.0), edge=0.2),))
    >>> c = tf_chart({"lo": 0.0, "hi": 100.0, "counts": [9, 0, 99, 0]}, spec)
    >>> c["structures"][0]["points"]
    '8.0,140.0 50.4,74.0 177.6,74.0 220.0,140.0'
    """
    from dvr_perception.app.session import rgb_to_hex

    lo, hi = float(histogram["lo"]), float(histogram["hi"])
    counts = np.asarray(histogram["counts"], float)
    logc = np.log10(1.0 + counts)
    top = float(logc.max()) if logc.size and logc.max() > 0 else 1.0
    n = max(len(counts), 1)
    base = _y(0.0)
    span = WIDTH - LEFT - RIGHT
    d = [f"M{_f(LEFT)},{_f(base)}"]
    for k, c in enumerate(logc):
        y = base - (base - TOP) * c / top
        d.append(f"L{_f(LEFT + span * k / n)},{_f(y)}L{_f(LEFT + span * (k + 1) / n)},{_f(y)}")
    d.append(f"L{_f(WIDTH - RIGHT)},{_f(base)}Z")
    ticks = [
        {"x": _f(LEFT + span * t), "label": f"{lo + (hi - lo) * t:.4g}", "anchor": anchor}
        for t, anchor in ((0.0, "start"), (0.5, "middle"), (1.0, "end"))
    ]
    rows = []
    for k, s in enumerate(spec.structures):
        if s.range is None:
            continue
        pts = _trapezoid(s, lo, hi)
        rows.append(
            {
                "index": k,
                "name": s.name,
                "color": rgb_to_hex(s.colour),
                "points": _points(pts),
                "x_lo": _f(pts[0][0]),
                "x_hi": _f(pts[3][0]),
                "x_mid": _f((pts[1][0] + pts[2][0]) / 2),
                "y_top": _f(pts[1][1]),
                "range": [round(float(v), 1) for v in s.range],
                "opacity": round(float(s.render_opacity), 3),
            }
        )
    old = []
    if before is not None:
        old = [
            {"points": _points(_trapezoid(s, lo, hi)), "color": rgb_to_hex(s.colour)}
            for s in before.structures
            if s.range is not None
        ]
    return {
        "width": WIDTH,
        "height": HEIGHT,
        "base": _f(base),
        "y_lo": _f(base - END_OFFSET),
        "y_hi": _f(base + END_OFFSET),
        "bars": "".join(d),
        "ticks": ticks,
        "structures": rows,
        "before": old,
    }


def dropped_edit(histogram: dict, spec, *, index, kind, fx, fy) -> dict:
    """Turn a handle dropped at ``(fx, fy)`` (fractions of the chart) into a structure edit.

    ``kind`` ``"lo"``/``"hi"`` moves that end of the range (kept inside the volume's values,
    above/below the other end and clear of the neighbouring structures' ranges, which may
    touch but not overlap); ``"opacity"`` sets the rendering opacity (0 to 1).

    Returns
    -------
    dict
        Keyword arguments for :meth:`Session.set_structure`: ``{"value_range": (lo, hi)}`` or
        ``{"opacity": a}``.

    Examples
    --------
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> spec = StructureSpec((Structure("a", 0.5, (1, 0, 0), range=(10.0, 50.0)),
    ...                       Structure("b", 0.5, (0, 1, 0), range=(60.0, 90.0))))
    >>> h = {"lo": 0.0, "hi": 100.0, "counts": [1]}
    >>> dropped_edit(h, spec, index=0, kind="hi", fx=0.9, fy=0.5)  # stops at b's range
    {'value_range': (10.0, 60.0)}
    >>> dropped_edit(h, spec, index=1, kind="opacity", fx=0.5, fy=TOP / HEIGHT)
    {'opacity': 1.0}
    """
    try:
        k = int(index)
        fx, fy = float(fx), float(fy)
    except (TypeError, ValueError):
        raise DVRInputError(f"transfer-function edit: bad handle position {fx!r}, {fy!r}") from None
    if not (math.isfinite(fx) and math.isfinite(fy)):
        raise DVRInputError(f"transfer-function edit: bad handle position {fx}, {fy}")
    if not 0 <= k < len(spec.structures):
        raise DVRInputError(f"transfer-function edit: no structure {index}")
    s = spec.structures[k]
    if kind == "opacity":
        a = 1.0 - (fy * HEIGHT - TOP) / (HEIGHT - TOP - BOTTOM)
        return {"opacity": round(min(max(a, 0.0), 1.0), 3)}
    if kind not in ("lo", "hi"):
        raise DVRInputError(f"transfer-function edit: unknown handle {kind!r}")
    if s.range is None:
        raise DVRInputError(f"{s.name}: a label structure has no value range")
    lo, hi = float(histogram["lo"]), float(histogram["hi"])
    t = (fx * WIDTH - LEFT) / (WIDTH - LEFT - RIGHT)
    value = lo + (hi - lo) * min(max(t, 0.0), 1.0)
    a, b = (float(v) for v in s.range)
    others = [o.range for j, o in enumerate(spec.structures) if j != k and o.range is not None]
    gap = (hi - lo) * 1e-3
    if kind == "lo":
        floor = max([o[1] for o in others if o[1] <= a] + [min(lo, a)])
        a = min(max(value, floor), b - gap)
    else:
        ceil = min([o[0] for o in others if o[0] >= b] + [max(hi, b)])
        b = max(min(value, ceil), a + gap)
    if _integer_valued(histogram):
        a, b = float(round(a)), float(round(b))
        if b <= a:  # keep the end that was not moved
            a, b = (b - 1.0, b) if kind == "lo" else (a, a + 1.0)
    return {"value_range": (a, b)}


def _integer_valued(histogram: dict) -> bool:
    """Whether a volume's values are spread wide enough to round dragged ends to integers."""
    return float(histogram["hi"]) - float(histogram["lo"]) >= 50.0


def colour_bar_stops(spec, histogram: dict) -> list[dict]:
    """Return the colour bar's stops: each range structure's colour over its range.

    Returns ``{"color", "start", "end", "name"}`` with ``start``/``end`` in percent of the
    volume's value range, lowest first.
    """
    from dvr_perception.app.session import rgb_to_hex

    lo, hi = float(histogram["lo"]), float(histogram["hi"])
    out = []
    for s in spec.structures:
        if s.range is None:
            continue
        a, b = ((float(v) - lo) / (hi - lo) * 100.0 for v in s.range)
        out.append(
            {
                "name": s.name,
                "color": rgb_to_hex(s.colour),
                "start": round(min(max(a, 0.0), 100.0), 2),
                "end": round(min(max(b, 0.0), 100.0), 2),
            }
        )
    return sorted(out, key=lambda r: r["start"])


def axis_camera(bounds, axis: str, *, width: int, height: int, view_angle: float = 30.0):
    """Return the camera looking at the volume's centre from ``axis`` (``"+X"`` ... ``"-Z"``).

    The whole volume fits the view (as ``Camera.from_view`` at zoom 1).

    Examples
    --------
    >>> cam = axis_camera((0, 10, 0, 10, 0, 10), "+X", width=64, height=64)
    >>> cam.position[0] > 10 and cam.position[1:] == (5.0, 5.0)
    True
    """
    from dvr_perception.rays import Camera

    if axis not in AXES:
        raise DVRInputError(f"view direction: expected one of {', '.join(AXES)}, got {axis!r}")
    b = np.asarray(bounds, float)
    if b.shape != (6,) or not np.all(np.isfinite(b)):
        raise DVRInputError(f"view direction: bounds must be 6 finite numbers, got {bounds}")
    centre = (b[0::2] + b[1::2]) / 2
    radius = 0.5 * float(np.linalg.norm(b[1::2] - b[0::2])) or 0.5
    dist = radius / math.sin(math.radians(view_angle) / 2.0)
    direction, up = (np.asarray(v) for v in AXES[axis])
    return Camera(
        position=tuple(centre + dist * direction),
        focal_point=tuple(centre),
        view_up=tuple(up),
        view_angle=view_angle,
        width=int(width),
        height=int(height),
    )
