"""Why the optimiser changed each structure, in words a clinician can read (issues 16, 30).

:func:`explain` gives every structure one consistent reason for its opacity, and says how
its shading and its colour changed and why, in perceptual terms; :func:`explanation_line`
and :func:`explanation_lines` print it.  The words name no measure (``E_v``, ``E_s``,
``E_t``) and no status code; ``verbose=True`` adds the measures' figures in brackets.

**Opacity.**  Shares of the picture and targets are image-wide (decisions D1 and D6): a
structure's share is its visible opacity summed over the picture, divided by that sum over
all structures; its target share the same of its target opacities.  An opacity counts as
changed when it prints differently with two decimals (so "kept" never stands beside a
printed change).  A structure whose opacity fell names what it traded against: the
structure behind it that needed more of the picture (below its target share), gained share,
and gained most from this fall (``covers``: how much of the picture each structure hides of
each other one, so a structure in front covers the one behind and not the reverse).  These
"covered" links never form a circle (not A for B and B for A, nor longer): links are taken
strongest first and one that would close a circle is dropped, and the structure then gets
its next link or the plain reason.  A structure below its target share that still loses
opacity says so ("lowered: although it had less of the picture than its target") and names
the trade; one that rose says it had less than its target.

**Shading** (the lighting stage): more directional or flatter shading (the ambient part of
the light), stronger or weaker, broader or tighter highlights, and where the light now comes
from; why: whether the structure's shape cues read better (its share of the shape measure
fell), or what it was traded for.  **Colour** (the colour stage): more or less saturated,
lighter or darker (a hue change only with ``allow_hue``); why: which overlapping structure it
moved away from in CIELAB so that the two are told apart, and whether it looks as
see-through as intended (its share of the transparency measure).
"""

from __future__ import annotations

import colorsys
import math
import warnings

import numpy as np

__all__ = ["explain", "explanation_line", "explanation_lines"]

#: Share differences smaller than this (absolute) count as "at the target" / "unchanged".
_NEAR = 0.01
#: A fall in opacity must uncover at least this share of the picture of the structure
#: behind to count as a trade for it.
MIN_GAIN = 0.002
#: A structure must share at least this fraction of the rays with another to be compared.
MIN_OVERLAP = 0.02
#: Material changes that count (absolute ambient, absolute specular, specular power ratio).
_AMBIENT, _SPECULAR, _POWER = 0.02, 0.05, 1.25
#: A light that moves less than this (degrees) has not moved.
_LIGHT_DEG = 3.0
#: Colour changes that count: HSV saturation and value, hue (turns), CIELAB distance (a
#: just noticeable difference is about 2.3); a colour that moved less than ``_LAB_SEEN`` has
#: not changed, one that moved less than ``_LAB`` is "barely visibly" changed.
_SAT, _VAL, _HUE, _LAB, _LAB_SEEN = 0.03, 0.03, 0.02, 2.0, 0.5


def _pct(x: float) -> str:
    return f"{100.0 * x:.0f} %"


# -- opacity -------------------------------------------------------------------------------------
def _changed(before: float, after: float) -> bool:
    """Whether an opacity prints differently (two decimals)."""
    return f"{before:.2f}" != f"{after:.2f}"


def _reaches(links: dict, start: int, goal: int) -> bool:
    """Say whether ``links`` (structure -> the one it was lowered for) lead from start to goal."""
    seen, cur = set(), start
    while cur in links and cur not in seen:
        seen.add(cur)
        cur = links[cur]
        if cur == goal:
            return True
    return cur == goal


def _trades(names, ops, before, after, target, covers) -> dict:
    """``{k: j}``: lowered structure ``k`` was traded for ``j`` (no circles; see the module)."""
    k = len(names)
    b = np.array([before[n] for n in names])
    a = np.array([after[n] for n in names])
    t = np.array([target[n] for n in names])
    drop = ops[0] - ops[1]
    cands = []
    for i in range(k):
        if not (_changed(ops[0][i], ops[1][i]) and drop[i] > 0):
            continue
        for j in range(k):
            if j == i or t[j] - b[j] <= _NEAR or a[j] <= b[j]:
                continue
            gain = covers[i, j] * drop[i]
            if gain >= MIN_GAIN:
                cands.append((-gain, i, j))
    links: dict = {}
    for _, i, j in sorted(cands):
        if i not in links and not _reaches(links, j, i):
            links[i] = j
    return links


def _opacity_reason(i, names, ops, before, after, target, links, covers, over) -> str:
    name = names[i]
    b, a, t = before[name], after[name], target[name]
    o0, o1 = ops[0][i], ops[1][i]
    if not _changed(o0, o1):
        if abs(a - b) >= _NEAR:
            return (
                f"kept: the other changes moved its share from {_pct(b)} to "
                f"{_pct(a)} (target {_pct(t)})"
            )
        if b < t - _NEAR and o0 >= 0.995:
            return (
                f"kept at full opacity: it has {_pct(b)} of the picture against a target of "
                f"{_pct(t)}, and it cannot be raised further"
            )
        return f"kept: it has {_pct(b)} of the picture against a target of {_pct(t)}"
    if o1 > o0:
        if b < t - _NEAR:
            text = (
                f"raised: it had less of the picture than its target ({_pct(b)} against {_pct(t)})"
            )
        else:
            text = "raised: where it shows, it was fainter than its importance asks for"
        if a < b - _NEAR:
            text += f"; the other changes still left it {_pct(a)}"
        return text
    j = links.get(i)
    if j is not None:
        other = names[j]
        lack = (
            f"{other}, which had less of the picture than its target ({_pct(before[other])} "
            f"against {_pct(target[other])})"
        )
        if b < t - _NEAR:
            text = (
                f"lowered: although it had less of the picture than its target ({_pct(b)} "
                f"against {_pct(t)}), it was traded for {lack} and lies behind it"
            )
        elif b > t + _NEAR:
            text = (
                f"lowered: it covered {lack}; it had more than its own target ({_pct(b)} "
                f"against {_pct(t)})"
            )
        else:
            text = f"lowered: it covered {lack}; it was at its own target ({_pct(t)})"
    elif b > t + _NEAR:
        return f"lowered: it had more of the picture than its target ({_pct(b)} against {_pct(t)})"
    else:
        if over is None or over[i] > 0:
            why = "where it shows it took more of the picture than its importance asks for"
        elif covers[i].max() * (o0 - o1) >= MIN_GAIN:
            why = "it was traded for what lies behind it"
        else:
            why = "the picture as a whole came closer to the intended shares with it fainter"
        if b < t - _NEAR:
            text = (
                f"lowered: although it had less of the picture than its target ({_pct(b)} "
                f"against {_pct(t)}), {why}"
            )
        else:
            text = f"lowered: {why}"
    if b < t - _NEAR and a > b + _NEAR:
        drop = ops[0] - ops[1]
        front = any(covers[j, i] * drop[j] >= MIN_GAIN for j in range(len(names)) if j != i)
        why = "what lies in front of it faded" if front else "the other changes left it more"
        text += f"; its share still rose to {_pct(a)} as {why}"
    elif b < t - _NEAR and a < b - _NEAR:
        text += f"; its share fell to {_pct(a)}"
    return text


# -- lighting ------------------------------------------------------------------------------------
def _direction(d) -> str:
    """Where a light in camera coordinates (x right, y up, z to the viewer) comes from."""
    x, y, z = (float(v) for v in np.asarray(d, float) / np.linalg.norm(d))
    az = math.degrees(math.atan2(x, z))
    el = math.degrees(math.asin(max(-1.0, min(1.0, y))))
    side = "left" if az <= -5 else "right" if az >= 5 else ""
    up = "upper" if el >= 5 else "lower" if el <= -5 else ""
    if z < 0:
        return "behind"
    if side and up:
        return f"the {up} {side}"
    if side:
        return f"the {side}"
    if up:
        return "above" if up == "upper" else "below"
    return "straight ahead"


def _light_move(d0, d1) -> str:
    """Say how the light moved: ``the light moved 12 degrees toward the upper left``."""
    u = np.asarray(d0, float) / np.linalg.norm(d0)
    v = np.asarray(d1, float) / np.linalg.norm(d1)
    dx, dy = v[:2] - u[:2]
    size = math.hypot(dx, dy)
    side = ("left" if dx < 0 else "right") if abs(dx) >= 0.35 * size else ""
    up = ("upper" if dy > 0 else "lower") if abs(dy) >= 0.35 * size else ""
    if side:
        toward = f"toward the {up} {side}" if up else f"toward the {side}"
    else:
        toward = "upward" if up == "upper" else "downward"
    now = _direction(v)
    text = f"the light moved {_angle(u, v):.0f} degrees {toward}"
    return text + (f" (now from {now})" if now != "straight ahead" else "")


def _angle(d0, d1) -> float:
    u = np.asarray(d0, float) / np.linalg.norm(d0)
    v = np.asarray(d1, float) / np.linalg.norm(d1)
    return math.degrees(math.acos(max(-1.0, min(1.0, float(u @ v)))))


def _join(parts: list[str]) -> str:
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]


def _better(x0, x1, i, eps) -> int:
    """-1 (fell: better), +1 (rose: worse) or 0 for entry ``i`` of two per-structure arrays."""
    if x0 is None or x1 is None:
        return 0
    u, v = float(x0[i]), float(x1[i])
    if not (math.isfinite(u) and math.isfinite(v)):
        return 0
    tol = max(eps, 0.02 * abs(u))
    return -1 if v < u - tol else 1 if v > u + tol else 0


def _best_gainer(x0, x1, names, i, eps) -> str | None:
    """Return the other structure whose figure fell most (better), if one did."""
    best, drop = None, 0.0
    for j, name in enumerate(names):
        if j != i and _better(x0, x1, j, eps) < 0 and float(x0[j] - x1[j]) > drop:
            best, drop = name, float(x0[j] - x1[j])
    return best


def _shading(i, names, lt, verbose) -> str | None:
    m0, m1 = np.asarray(lt["materials_before"], float), np.asarray(lt["materials_after"], float)
    amb0, _, spec0, pow0 = m0[i]
    amb1, _, spec1, pow1 = m1[i]
    how = []
    if amb1 < amb0 - _AMBIENT:
        how.append("more directional shading")
    elif amb1 > amb0 + _AMBIENT:
        how.append("flatter shading")
    spot = []
    if spec1 > spec0 + _SPECULAR:
        spot.append("stronger")
    elif spec1 < spec0 - _SPECULAR:
        spot.append("weaker")
    if max(spec0, spec1) >= _SPECULAR:
        if pow1 * _POWER < pow0:
            spot.append("broader")
        elif pow1 > pow0 * _POWER:
            spot.append("tighter")
    if spot:
        how.append(" and ".join(spot) + " highlights")
    l0, l1 = lt.get("light_before"), lt.get("light_after")
    moved = l0 is not None and l1 is not None and _angle(l0, l1) >= _LIGHT_DEG
    if not how and not moved:
        return None
    if moved:
        how.append(_light_move(l0, l1))
    s0, s1 = lt.get("shape_before"), lt.get("shape_after")
    verdict = _better(s0, s1, i, 0.005)
    if verdict < 0:
        text = f"{_join(how)}; its shape reads better than under the old lighting"
    elif verdict > 0:
        text = f"{_join(how)}; its shape reads a little less clearly than under the old lighting"
        other = _best_gainer(s0, s1, names, i, 0.005)
        if other is not None:
            text += f", traded for the shape of {other}, which reads better"
    elif s0 is None or s1 is None:
        text = _join(how)
    else:
        text = f"{_join(how)}; its shape reads about as well as under the old lighting"
    if verbose and s0 is not None and s1 is not None:
        text += f" [E_s on its pixels {float(s0[i]):.3f} -> {float(s1[i]):.3f}]"
    return text


# -- colour --------------------------------------------------------------------------------------
def _lab(rgb) -> np.ndarray:
    """CIELAB (D65) of an sRGB colour in [0, 1]."""
    c = np.clip(np.asarray(rgb, float), 0.0, 1.0)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = m @ lin / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def _dist(c0, c1) -> float:
    return float(np.linalg.norm(_lab(c0) - _lab(c1)))


def _colour(i, names, cl, overlap, verbose) -> str | None:
    c0, c1 = np.asarray(cl["colours_before"], float), np.asarray(cl["colours_after"], float)
    size = _dist(c0[i], c1[i])
    if size < _LAB_SEEN:
        return None
    h0, s0, v0 = colorsys.rgb_to_hsv(*np.clip(c0[i], 0, 1))
    h1, s1, v1 = colorsys.rgb_to_hsv(*np.clip(c1[i], 0, 1))
    how = []
    if abs((h1 - h0 + 0.5) % 1.0 - 0.5) >= _HUE and min(s0, s1) > 0.05:
        how.append("a different hue")
    if s1 >= s0 + _SAT:
        how.append("more saturated")
    elif s1 <= s0 - _SAT:
        how.append("paler")
    if v1 >= v0 + _VAL:
        how.append("lighter")
    elif v1 <= v0 - _VAL:
        how.append("darker")
    if not how:
        how.append("a barely visible change" if size < _LAB else "a slightly different shade")
    elif size < _LAB:
        how = ["barely visibly " + _join(how)]
    # the overlapping structure this colour moved away from most (its own move, against the
    # other's final colour)
    apart, best = None, _LAB
    for j, other in enumerate(names):
        if j == i or overlap[i, j] < MIN_OVERLAP:
            continue
        gain = _dist(c1[i], c1[j]) - _dist(c0[i], c1[j])
        if gain >= best:
            apart, best = other, gain
    why = []
    if apart is not None:
        why.append(f"it moved away from the colour of {apart}, so the two are told apart where "
                   "they overlap")  # fmt: skip
    t0, t1 = cl.get("transparency_before"), cl.get("transparency_after")
    verdict = _better(t0, t1, i, 1e-3)
    other = _best_gainer(t0, t1, names, i, 1e-3)
    if verdict < 0:
        why.append("how see-through it looks is closer to what is intended")
    elif verdict > 0:
        why.append(
            "how see-through it looks is a little further from what is intended"
            + (f", traded for {other}, which comes closer" if other else "")
        )
    shaped = _better(cl.get("shape_before"), cl.get("shape_after"), i, 0.005)
    if shaped < 0:
        why.append("its shape reads better than in its old shade")
    if not why and other is not None:
        why.append(
            f"part of the change that brought how see-through {other} looks closer to what "
            "is intended"
        )
    if not why:
        why.append("it reads about as before")
    text = "; ".join([_join(how), *why])
    if verbose and t0 is not None and t1 is not None:
        extra = ""
        if cl.get("shape_before") is not None and cl.get("shape_after") is not None:
            u, v = float(cl["shape_before"][i]), float(cl["shape_after"][i])
            extra = f"; E_s on its pixels {u:.3f} -> {v:.3f}"
        text += f" [E_t of its layers {float(t0[i]):.4f} -> {float(t1[i]):.4f}{extra}]"
    return text


# -- the whole explanation -----------------------------------------------------------------------
def explain(names, opacities_before, opacities_after, shares_before, shares_after,
            target_shares, covers=None, *, lighting=None, colour=None, overlap=None,
            over=None) -> dict:  # fmt: skip
    """Per structure: opacity and share of the picture before and after, target, the reasons.

    Parameters
    ----------
    names : sequence of str
    opacities_before, opacities_after : array_like, shape (K,)
        Rendering opacities.
    shares_before, shares_after, target_shares : dict
        ``{name: share}`` of the picture (image-wide visible opacity, D1/D6) and the target
        share.
    covers : array_like, shape (K, K), optional
        ``covers[k, j]``: the share of the picture structure ``j`` gains per unit that
        ``k``'s opacity falls (``k`` in front of ``j``; 0 where ``k`` hides nothing of ``j``).
        Default: every structure may cover every other one by 1.
    lighting : dict, optional
        ``materials_before``, ``materials_after`` ((K, 4): ambient, diffuse, specular,
        specular power), ``light_before``, ``light_after`` (camera coordinates: x right,
        y up, z to the viewer) and optionally ``shape_before``, ``shape_after`` ((K,): each
        structure's shape mismatch, lower is better, across the lighting stage).
    colour : dict, optional
        ``colours_before``, ``colours_after`` ((K, 3) RGB in [0, 1]; the keys
        ``colors_before``, ``colors_after`` are deprecated aliases) and optionally
        ``transparency_before``, ``transparency_after`` ((K,): each structure's mismatch of
        perceived transparency, lower is better, across the colour stage) and
        ``shape_before``, ``shape_after`` (its shape mismatch across the colour stage).
    overlap : array_like, shape (K, K), optional
        Fraction of the rays on which both structures lie (which colours are compared);
        default: ``covers + covers.T`` where given, else all 1.
    over : array_like, shape (K,), optional
        Positive where a structure, where it shows, was more opaque than its target opacity
        at the start (:meth:`~dvr_perception.optimize._exact.OpacityModel.covering`'s
        ``own``): the reason of a fall that traded for no one (default: assumed).

    Returns
    -------
    dict
        ``{name: {"opacity_before", "opacity_after", "share_before", "target_share",
        "share_after", "reason", "traded_for", "shading", "colour", "shading_verbose",
        "colour_verbose"}}``; ``traded_for`` is the structure a lowered one was traded for
        (or ``None``), ``shading`` and ``colour`` are ``None`` where nothing changed.

    Examples
    --------
    >>> covers = [[0.0, 0.5], [0.0, 0.0]]  # the skin lies in front of the bone
    >>> out = explain(["skin", "bone"], [0.8, 0.5], [0.3, 0.5], {"skin": 0.9, "bone": 0.1},
    ...               {"skin": 0.6, "bone": 0.4}, {"skin": 0.5, "bone": 0.5}, covers)
    >>> out["skin"]["reason"]
    'lowered: it covered bone, which had less of the picture than its target (10 % against 50 %); it had more than its own target (90 % against 50 %)'
    >>> out["bone"]["reason"]
    'kept: the other changes moved its share from 10 % to 40 % (target 50 %)'
    """  # noqa: E501
    names = list(names)
    k = len(names)
    ops = (np.asarray(opacities_before, float), np.asarray(opacities_after, float))
    if covers is None:
        cov = np.ones((k, k)) - np.eye(k)
    else:
        cov = np.clip(np.asarray(covers, float), 0.0, None)
    over_k = None if over is None else np.asarray(over, float)
    if colour is not None and ("colors_before" in colour or "colors_after" in colour):
        warnings.warn(
            "explain(colour=...): the keys 'colors_before', 'colors_after' are deprecated; "
            "use 'colours_before', 'colours_after'",
            DeprecationWarning,
            stacklevel=2,
        )
        colour = {key.replace("colors_", "colours_", 1): v for key, v in colour.items()}
    if overlap is None:
        both = cov + cov.T if covers is not None else np.ones((k, k))
    else:
        both = np.asarray(overlap, float)
    links = _trades(names, ops, shares_before, shares_after, target_shares, cov)
    out = {}
    for i, name in enumerate(names):
        entry = {
            "opacity_before": float(ops[0][i]),
            "opacity_after": float(ops[1][i]),
            "share_before": float(shares_before[name]),
            "target_share": float(target_shares[name]),
            "share_after": float(shares_after[name]),
            "reason": _opacity_reason(
                i, names, ops, shares_before, shares_after, target_shares, links, cov, over_k
            ),
            "traded_for": names[links[i]] if i in links else None,
        }
        for key, fn, data in (("shading", _shading, lighting), ("colour", _colour, colour)):
            if data is None:
                entry[key] = entry[f"{key}_verbose"] = None
                continue
            args = (i, names, data) if key == "shading" else (i, names, data, both)
            entry[key] = fn(*args, verbose=False)
            entry[f"{key}_verbose"] = fn(*args, verbose=True)
        out[name] = entry
    return out


def explanation_lines(name: str, entry: dict, *, verbose: bool = False) -> list[str]:
    """Return the structure's lines: opacity and share of the picture, then shading, colour.

    Examples
    --------
    >>> e = {"opacity_before": 0.5, "opacity_after": 0.2, "share_before": 0.8,
    ...      "share_after": 0.5, "target_share": 0.4, "reason": "lowered: ...",
    ...      "shading": "broader highlights; its shape reads better", "colour": None}
    >>> for line in explanation_lines("skin", e):
    ...     print(line)
    skin: opacity 0.50 -> 0.20; share of the picture 80 % -> 50 % (target 40 %); lowered: ...
    shading: broader highlights; its shape reads better
    """
    lines = [
        f"{name}: opacity {entry['opacity_before']:.2f} -> {entry['opacity_after']:.2f}; "
        f"share of the picture {_pct(entry['share_before'])} -> {_pct(entry['share_after'])} "
        f"(target {_pct(entry['target_share'])}); {entry['reason']}"
    ]
    for key in ("shading", "colour"):
        text = entry.get(f"{key}_verbose") if verbose else None
        text = text or entry.get(key)
        if text:
            lines.append(f"{key}: {text}")
    return lines


def explanation_line(name: str, entry: dict, *, verbose: bool = False) -> str:
    """Return :func:`explanation_lines` joined with ``"; "`` (what the app and ParaView show)."""
    return "; ".join(explanation_lines(name, entry, verbose=verbose))
