"""Matplotlib charts of measure results and optimisation progress (figures are returned).

The figures use the ``Figure`` object API (no pyplot state), so they work headless; save them
with ``fig.savefig(path)``.
"""

from __future__ import annotations

import math

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.structures.spec import printable

__all__ = ["plot_convergence", "plot_visibility_histograms"]

#: Terms drawn by :func:`plot_convergence` when present.
CONVERGENCE_TERMS = ("E", "E_v", "E_s", "E_t")


def plot_visibility_histograms(vis_result):
    """Per structure, histograms of the per-ray visible and assigned opacity shares.

    Parameters
    ----------
    vis_result : VisibilityResult
        From :func:`dvr_perception.measures.visibility`.

    Returns
    -------
    matplotlib.figure.Figure
        One axes per structure (bars: visible; outline: assigned).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> hist = {"histogram_visible": [3, 1], "histogram_assigned": [1, 3]}
    >>> vis = SimpleNamespace(per_structure={"a": hist}, bin_edges=np.array([0, 0.5, 1]),
    ...                       E_v=0.4)
    >>> len(plot_visibility_histograms(vis).axes)
    1
    """
    from matplotlib.figure import Figure

    per = getattr(vis_result, "per_structure", None)
    edges = getattr(vis_result, "bin_edges", None)
    if not isinstance(per, dict) or edges is None or not per:
        raise DVRInputError(
            "vis_result: expected a VisibilityResult with per_structure histograms, got "
            f"{type(vis_result).__name__}"
        )
    edges = np.asarray(edges, dtype=np.float64)
    n = len(per)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(3.2 * cols, 2.6 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    centres, widths = 0.5 * (edges[1:] + edges[:-1]), np.diff(edges)
    for ax, (name, d) in zip(axes, per.items(), strict=False):
        vis = np.asarray(d["histogram_visible"], dtype=np.float64)
        asg = np.asarray(d["histogram_assigned"], dtype=np.float64)
        ax.bar(centres, vis, width=widths, alpha=0.6, label="visible")
        ax.step(edges, np.append(asg, asg[-1:]), where="post", color="k", label="assigned")
        ax.set_title(printable(name, 32).replace("$", r"\$"))  # never mathtext
        ax.set_xlabel("share of ray opacity")
        ax.set_ylabel("rays")
    for ax in axes[n:]:
        fig.delaxes(ax)
    axes[0].legend(fontsize="small")
    e_v = getattr(vis_result, "E_v", None)
    if e_v is not None:
        fig.suptitle(f"visibility: E_v = {float(e_v):.3f}")
    return fig


def _history_entries(history) -> list[dict]:
    stages = getattr(history, "stages", None)
    if stages is not None:
        history = stages
    entries: list[dict] = []
    for item in history:
        sub = getattr(item, "history", None)
        if sub is not None:
            stage = getattr(item, "name", "")
            entries.extend({**e, "stage": stage} for e in sub)
        elif isinstance(item, dict):
            entries.append(item)
        else:
            raise DVRInputError(
                "history: expected an OptimizationResult, stage records or dicts of terms, "
                f"got an item of type {type(item).__name__}"
            )
    return entries


def plot_convergence(history):
    """Objective terms per iteration over all stages (stage boundaries marked).

    Parameters
    ----------
    history : OptimizationResult or sequence of StageRecord or sequence of dict
        Dicts carry the terms ``E``, ``E_v``, ``E_s``, ``E_t`` (any subset) and optionally
        ``stage``.

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> fig = plot_convergence([{"E": 1.0, "E_v": 0.5}, {"E": 0.8, "E_v": 0.4}])
    >>> [line.get_label() for line in fig.axes[0].get_lines()]
    ['E', 'E_v']
    """
    from matplotlib.figure import Figure

    try:
        entries = _history_entries(history)
    except TypeError:
        raise DVRInputError(
            f"history: expected an iterable of iterations, got {type(history).__name__}"
        ) from None
    if not entries:
        raise DVRInputError("history: no iterations to plot")
    fig = Figure(figsize=(6.0, 3.5), layout="constrained")
    ax = fig.subplots()
    x = np.arange(1, len(entries) + 1)
    for term in CONVERGENCE_TERMS:
        if any(term in e for e in entries):
            y = [float(e[term]) if term in e else np.nan for e in entries]
            ax.plot(x, y, label=term, linewidth=2.0 if term == "E" else 1.2)
    stages = [e.get("stage") for e in entries]
    for i in range(1, len(stages)):
        if stages[i] != stages[i - 1]:
            ax.axvline(i + 0.5, color="0.7", linestyle="--", linewidth=0.8)
    ax.set_xlabel("iteration (all stages)")
    ax.set_ylabel("term value")
    ax.legend(fontsize="small")
    return fig
