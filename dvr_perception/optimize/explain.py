"""Why the optimiser changed each structure: one line per structure, in words (issue 16).

:func:`explain` compares a structure's rendering opacity and its share of the picture before
and after an optimisation with its target share (decision D1: the image-wide share of the
target opacities ``alpha_o``) and names the reason: a structure whose opacity fell is said to
have *covered* the structure that most needed picture (one below its target share that lies on
the same rays and gained share), else to have had more than its target; a structure whose
opacity rose had less than its target.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KEPT", "explain", "explanation_line"]

#: Opacity changes smaller than this (absolute) count as "kept".
KEPT = 0.01
#: Share differences smaller than this (absolute) count as "at the target".
_NEAR = 0.01


def _pct(x: float) -> str:
    return f"{100.0 * x:.0f} %"


def _reason(k, names, ops, before, after, target, copresence) -> str:
    name = names[k]
    d_op = ops[1][k] - ops[0][k]
    b, t = before[name], target[name]
    if abs(d_op) < KEPT:
        a = after[name]
        if abs(a - b) >= _NEAR:
            return (
                f"kept: the other changes moved its share from {_pct(b)} to {_pct(a)} of the "
                f"picture (target {_pct(t)})"
            )
        return f"kept: it has {_pct(b)} of the picture against a target of {_pct(t)}"
    if d_op > 0:
        if b < t - _NEAR:
            return f"raised: it had {_pct(b)} of the picture against a target of {_pct(t)}"
        return "raised: on the rays it crosses it showed less than its target opacity"
    best, score = None, 0.0
    for j, other in enumerate(names):
        need = target[other] - before[other]
        if j == k or need <= _NEAR or after[other] <= before[other]:
            continue
        if copresence[k, j] * need > score:
            best, score = other, copresence[k, j] * need
    if best is not None:
        return (
            f"lowered: it covered {best}, which had {_pct(before[best])} of the picture "
            f"against a target of {_pct(target[best])}"
        )
    if b > t + _NEAR:
        return f"lowered: it had {_pct(b)} of the picture against a target of {_pct(t)}"
    return "lowered: on the rays it crosses it showed more than its target opacity"


def explain(names, opacities_before, opacities_after, shares_before, shares_after,
            target_shares, copresence=None) -> dict:  # fmt: skip
    """Per structure: opacity and share of the picture before and after, target, reason.

    Parameters
    ----------
    names : sequence of str
    opacities_before, opacities_after : array_like, shape (K,)
        Rendering opacities.
    shares_before, shares_after, target_shares : dict
        ``{name: share}`` of the picture (visible opacity, image-wide) and the target share.
    copresence : array_like, shape (K, K), optional
        Fraction of the rays on which both structures are present (default: all 1).

    Returns
    -------
    dict
        ``{name: {"opacity_before", "opacity_after", "share_before", "target_share",
        "share_after", "reason"}}``.

    Examples
    --------
    >>> out = explain(["skin", "bone"], [0.8, 0.5], [0.3, 0.5], {"skin": 0.9, "bone": 0.1},
    ...               {"skin": 0.6, "bone": 0.4}, {"skin": 0.5, "bone": 0.5})
    >>> out["skin"]["reason"]
    'lowered: it covered bone, which had 10 % of the picture against a target of 50 %'
    >>> out["bone"]["reason"]
    'kept: the other changes moved its share from 10 % to 40 % of the picture (target 50 %)'
    """
    names = list(names)
    k = len(names)
    ops = (np.asarray(opacities_before, float), np.asarray(opacities_after, float))
    co = np.ones((k, k)) if copresence is None else np.asarray(copresence, float)
    out = {}
    for i, name in enumerate(names):
        out[name] = {
            "opacity_before": float(ops[0][i]),
            "opacity_after": float(ops[1][i]),
            "share_before": float(shares_before[name]),
            "target_share": float(target_shares[name]),
            "share_after": float(shares_after[name]),
            "reason": _reason(i, names, ops, shares_before, shares_after, target_shares, co),
        }
    return out


def explanation_line(name: str, entry: dict) -> str:
    """One line: ``name: opacity a -> b; share of the picture x -> target y -> z; reason``."""
    return (
        f"{name}: opacity {entry['opacity_before']:.2f} -> {entry['opacity_after']:.2f}; "
        f"share of the picture {_pct(entry['share_before'])} -> target "
        f"{_pct(entry['target_share'])} -> {_pct(entry['share_after'])}; {entry['reason']}"
    )
