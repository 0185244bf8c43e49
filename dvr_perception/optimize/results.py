"""Result containers of :func:`~dvr_perception.optimize.optimize` (scipy.optimize style).

``terms`` dicts everywhere have the keys ``E_v``, ``E_s``, ``E_t`` (the three measures),
``E`` (Eq. 12 with the user's weights), ``coverage`` (mean accumulated opacity over the rays
that carry assigned opacity) and ``visible_share`` (``{structure: share of the accumulated
opacity}``).  With a region they are taken inside the region.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from dvr_perception.structures.spec import StructureSpec

__all__ = ["STATUS_MESSAGES", "IntermediateResult", "OptimizationResult", "StageRecord"]

#: ``status`` -> meaning.
STATUS_MESSAGES = {
    0: "every stage converged",
    1: "stopped by the callback (StopIteration); best parameters so far returned",
    2: "a stage reached max_iter before converging",
}


@dataclass(frozen=True)
class IntermediateResult:
    """What a callback receives after every iteration (a copy; changing it changes nothing).

    Attributes
    ----------
    stage : str
        Name of the running stage.
    iteration : int
        Iteration within the stage (from 1).
    nit, nfev : int
        Iterations and objective evaluations so far over all stages.
    terms : dict
        Terms of the current iterate (at the optimisation resolution).
    best_terms : dict
        Terms of the best feasible iterate of the stage so far.
    spec : StructureSpec
        The current iterate as a spec.
    """

    stage: str
    iteration: int
    nit: int
    nfev: int
    terms: dict
    best_terms: dict
    spec: StructureSpec


@dataclass(frozen=True)
class StageRecord:
    """What one stage did.

    Attributes
    ----------
    name : str
        Stage name.
    params_before, params_after : dict
        The stage's parameters (see ``Stage.describe``) before and after.
    terms_before, terms_after : dict
        Terms before and after the stage at the optimisation resolution (the user's when it
        is not above ``resolution``); also ``luminance`` (``{structure: mean footprint
        luminance}``).
    iterations, evaluations : int
        Iterations (CG steps and annealing moves) and objective evaluations.
    seconds : float
        Wall time of the stage.
    history : tuple of dict
        Per iteration, the current iterate's terms at the optimisation resolution plus
        ``iteration``, ``kind`` ("cg", "anneal", "anneal (rejected)"), ``f`` (the stage
        objective with the boosted lead weight and the penalty), ``penalty`` and ``best_f``.
    converged : bool
        Whether the stage converged (rather than hitting ``max_iter`` or being stopped).
    accepted : bool
        False when the result failed the final check at the user's resolution and this stage
        was undone (``params_after`` is then what the stage had found, not what was kept).
    message : str
    """

    name: str
    params_before: dict
    params_after: dict
    terms_before: dict
    terms_after: dict
    iterations: int
    evaluations: int
    seconds: float
    history: tuple
    converged: bool
    accepted: bool
    message: str


@dataclass(frozen=True)
class OptimizationResult:
    """Result of :func:`~dvr_perception.optimize.optimize`.

    Attributes
    ----------
    spec : StructureSpec
        The optimised spec: rendering opacities in ``Structure.opacity``, materials in
        ``Structure.lighting``, colours in ``Structure.colour``, the light direction in
        ``rendering.light_direction``.
    initial, final : dict
        Terms (see the module docstring) at the user's resolution before and after, averaged
        over the views; ``"whole"`` holds the whole-image ``E_v``, ``E_s``, ``E_t``, ``E``
        (equal to the top-level ones without a region).
    stages : tuple of StageRecord
        One record per stage run, in order.
    nit, nfev : int
        Total iterations and objective evaluations (all resolutions).
    seconds : float
        Total wall time, including the ray analyses.
    status : int
        See :data:`STATUS_MESSAGES`.
    message : str
    success : bool
        ``status == 0``.
    structures : dict
        Per structure, why it changed (:func:`~dvr_perception.optimize.explain.explain`):
        opacity before and after, share of the picture before, target and after, reason.
    analyses : tuple
        ``(before, after)``: the first view's :class:`~dvr_perception.rays.engine.RayAnalysis`
        at the user's resolution with the input spec and with ``spec`` (re-composited from
        the optimiser's cache: equal to a fresh ``analyze``); empty when not kept.
    measures : tuple
        ``(before, after)``: ``all_measures`` of ``analyses`` with the input spec and with
        ``spec`` (:class:`~dvr_perception.measures.MeasureSet`), with ``optimize(...,
        measures=True)``; else empty.
    """

    spec: StructureSpec
    initial: dict
    final: dict
    stages: tuple
    nit: int
    nfev: int
    seconds: float
    status: int
    message: str
    success: bool
    structures: dict = field(default_factory=dict)
    analyses: tuple = field(default=(), repr=False, compare=False)
    measures: tuple = field(default=(), repr=False, compare=False)
