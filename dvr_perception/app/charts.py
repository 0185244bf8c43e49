"""Small SVG charts for the page, built on the server from numbers only (no user text)."""

from __future__ import annotations

import math

__all__ = ["calibration_svg", "lines_svg"]


def _fmt(v: float) -> str:
    return f"{v:.1f}"


def lines_svg(series, *, width: int = 400, height: int = 64) -> str:
    """Return a chart of several series as an SVG string (e.g. the errors per iteration).

    ``series`` is a list of ``(label, colour, values)``; all share one y-axis, whose range is
    written at the left.

    Examples
    --------
    >>> lines_svg([("E_v", "#1565c0", [1.0, 0.5])]).startswith("<svg")
    True
    """
    clean = [
        (label, color, [float(v) for v in values if v is not None and math.isfinite(float(v))])
        for label, color, values in series
    ]
    allv = [v for _, _, vals in clean for v in vals]
    left, pad = 40, 5
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="100%" height="{height + 18}" '
        f'viewBox="0 0 {width} {height + 18}">',
        f'<rect x="{left}" y="0" width="{width - left}" height="{height}" fill="#f5f5f5"/>',
    ]
    if allv:
        lo, hi = min(allv), max(allv)
        if hi - lo < 1e-12:  # flat lines in the middle, not along the border
            lo, hi = lo - 0.5 * abs(lo or 1.0), hi + 0.5 * abs(hi or 1.0)
        span = hi - lo
        style = 'font-size="11" font-family="sans-serif" fill="#616161"'
        parts.append(f'<text x="2" y="11" {style}>{hi:.3g}</text>')
        parts.append(f'<text x="2" y="{height - 2}" {style}>{lo:.3g}</text>')
        n = max(max(len(vals) for _, _, vals in clean) - 1, 1)
        for _label, color, vals in clean:
            if not vals:
                continue
            pts = [
                (
                    left + pad + (width - left - 2 * pad) * k / n,
                    pad + (height - 2 * pad) * (hi - v) / span,
                )
                for k, v in enumerate(vals)
            ]
            text = " ".join(f"{_fmt(x)},{_fmt(y)}" for x, y in pts)
            parts.append(
                f'<polyline points="{text}" fill="none" stroke="{color}" stroke-width="2"/>'
            )
            for x, y in pts:
                parts.append(f'<circle cx="{_fmt(x)}" cy="{_fmt(y)}" r="2.5" fill="{color}"/>')
        x = left
        for label, color, _vals in clean:
            parts.append(f'<rect x="{x}" y="{height + 6}" width="10" height="10" fill="{color}"/>')
            parts.append(f'<text x="{x + 14}" y="{height + 15}" {style}>{label}</text>')
            x += 14 + 8 * len(label) + 16
    parts.append("</svg>")
    return "".join(parts)


def calibration_svg(curve=None, measured=(), ratings=(), *, size: int = 320) -> str:
    """Chart of a calibration: the identity (grey), the ratings (dots) and the fitted curve.

    x: measured see-through (transmittance), y: what the viewer saw; both 0 to 1.
    """
    pad = 34
    inner = size - 2 * pad

    def px(x, y):
        return _fmt(pad + inner * x), _fmt(pad + inner * (1.0 - y))

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" '
        f'viewBox="0 0 {size} {size}">',
        f'<rect x="{pad}" y="{pad}" width="{inner}" height="{inner}" fill="#fafafa" '
        'stroke="#9e9e9e"/>',
    ]
    x0, y0 = px(0, 0)
    x1, y1 = px(1, 1)
    parts.append(
        f'<line x1="{x0}" y1="{y0}" x2="{x1}" y2="{y1}" stroke="#bdbdbd" stroke-dasharray="4 3"/>'
    )
    for m, r in zip(measured, ratings, strict=False):
        cx, cy = px(float(m), float(r))
        parts.append(f'<circle cx="{cx}" cy="{cy}" r="3.5" fill="#ef6c00"/>')
    if curve is not None:
        pts = " ".join(",".join(px(x, y)) for x, y in zip(curve.x, curve.y, strict=True))
        parts.append(f'<polyline points="{pts}" fill="none" stroke="#1565c0" stroke-width="2"/>')
    style = 'font-size="13" font-family="sans-serif" fill="#424242"'
    parts.append(f'<text x="{pad}" y="{size - 8}" {style}>measured see-through (0 to 1)</text>')
    parts.append(
        f'<text x="12" y="{size - pad}" {style} transform="rotate(-90 12 {size - pad})">'
        "what you saw (0 to 1)</text>"
    )
    parts.append("</svg>")
    return "".join(parts)
