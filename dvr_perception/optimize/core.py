"""The front door of the optimiser: :func:`optimize` (paper, Sec. 5-6)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from dvr_perception._progress import reporter
from dvr_perception.errors import DVRInputError
from dvr_perception.measures import all_measures, calibrate
from dvr_perception.measures.visibility import COMPOSITIONS
from dvr_perception.optimize._exact import OpacityModel
from dvr_perception.optimize._problem import Params, Problem, public_terms
from dvr_perception.optimize._region import parse_region, parse_targets, resample_mask
from dvr_perception.optimize._solver import run_stage
from dvr_perception.optimize.explain import explain
from dvr_perception.optimize.results import (
    STATUS_MESSAGES,
    IntermediateResult,
    OptimizationResult,
    StageRecord,
)
from dvr_perception.optimize.stages import STAGES
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature_field import curvature_source
from dvr_perception.rays.engine import BACKENDS, analyze_views, release_scratch
from dvr_perception.structures.spec import StructureSpec
from dvr_perception.volume.volume import Volume

__all__ = ["DEFAULT_RESOLUTION", "OBJECTIVES", "optimize"]

#: The scalar each stage minimises and the final check guards (decision D4): the weighted
#: image means ``E`` (Eq. 12) or Eq. 13's least-squares residue ``S`` per pixel.
OBJECTIVES = ("mean", "least_squares")
#: objective -> the terms key that may never rise.
_KEY = {"mean": "E", "least_squares": "S"}

#: Slack of the re-check of the stages' guards at the user's resolution (the opacity stage
#: checks its coverage floor there exactly, so only float rounding).
GUARD_SLACK = 1e-6
#: Fractions of a stage's step retried at the user's resolution when the whole step fails there.
SHORTER = (0.5, 0.25)

#: Long side, in pixels, of the camera the optimiser evaluates on (when ``resolution=None``).
DEFAULT_RESOLUTION = 96

#: Long side, in pixels, of the camera of the finite differences of the lighting and colour
#: stages (the rays subsampled; only when the optimisation resolution is at least twice it).
FD_RESOLUTION = 48


def _check(volume, spec, camera, stages, weights, cameras, region, calibration, seed, callback,
           max_iter, resolution, opacity_floor, coverage_keep=None, analyzer=None):  # fmt: skip
    if analyzer is not None:
        if not callable(analyzer):
            raise DVRInputError(f"analyzer: expected a callable or None, got {analyzer!r}")
    elif not isinstance(volume, Volume):
        raise DVRInputError(f"volume: expected a Volume, got {type(volume).__name__}")
    if not isinstance(spec, StructureSpec):
        raise DVRInputError(f"spec: expected a StructureSpec, got {type(spec).__name__}")
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    if isinstance(stages, str) or not isinstance(stages, Sequence) or not stages:
        raise DVRInputError(f"stages: expected a non-empty sequence of stage names, got {stages!r}")
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        raise DVRInputError(f"stages: unknown stage(s) {unknown}; known stages: {sorted(STAGES)}")
    try:
        w = np.array([float(v) for v in weights])
    except (TypeError, ValueError):
        raise DVRInputError(
            f"weights: expected 3 numbers (w_v, w_s, w_t), got {weights!r}"
        ) from None
    if w.shape != (3,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
        raise DVRInputError(
            "weights: expected 3 finite numbers (w_v, w_s, w_t) >= 0, not all zero, "
            f"got {weights!r}"
        )
    if cameras is not None:
        if isinstance(cameras, Camera) or not isinstance(cameras, Sequence):
            raise DVRInputError("cameras: expected a list of Camera (further views)")
        if not all(isinstance(c, Camera) for c in cameras):
            raise DVRInputError("cameras: every entry must be a Camera")
        if region is not None and len(cameras):
            raise DVRInputError("cameras: a region refines one view; give region or cameras")
    if calibration is not None:
        try:
            calibrate(0.5, calibration)
        except DVRInputError as err:
            raise DVRInputError(f"calibration: {err}") from None
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise DVRInputError(f"seed: expected an integer >= 0, got {seed!r}")
    if callback is not None and not callable(callback):
        raise DVRInputError(f"callback: expected a callable or None, got {callback!r}")
    for name, value, lo in (("max_iter", max_iter, 1), ("resolution", resolution, 8)):
        if value is None and name == "resolution":
            continue
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
            raise DVRInputError(f"{name}: expected an integer >= {lo}, got {value!r}")
    if opacity_floor is not None and not (
        isinstance(opacity_floor, (int, float)) and 0.0 <= float(opacity_floor) <= 1.0
    ):
        raise DVRInputError(f"opacity_floor: expected a number in [0, 1], got {opacity_floor!r}")
    if coverage_keep is not None:
        if isinstance(coverage_keep, bool) or not (
            isinstance(coverage_keep, (int, float)) and 0.0 <= float(coverage_keep) <= 1.0
        ):
            raise DVRInputError(
                f"coverage_keep: expected a number in [0, 1], got {coverage_keep!r}"
            )
        if opacity_floor is not None:
            raise DVRInputError("coverage_keep: give opacity_floor or coverage_keep, not both")
    return w


def _reduced(camera: Camera, resolution: int) -> Camera:
    long = max(camera.width, camera.height)
    if long <= resolution:
        return camera
    s = resolution / long
    return camera.with_size(max(8, round(camera.width * s)), max(8, round(camera.height * s)))


def _report(problem: Problem, params: Params, region: bool, terms: dict) -> dict:
    out = public_terms(terms, problem.names)
    whole = problem.terms(params, whole=True) if region else terms
    out["whole"] = {k: whole[k] for k in ("E_v", "E_s", "E_t", "E", "S")}
    return out


def optimize(
    volume,
    spec,
    camera,
    *,
    stages=("opacity", "lighting", "colour"),
    weights=(1.0, 1.0, 1.0),
    region=None,
    targets=None,
    calibration=None,
    cameras=None,
    seed=0,
    callback=None,
    max_iter=5,
    resolution=None,
    opacity_floor=None,
    coverage_keep=None,
    allow_hue=False,
    curvature=None,
    composition="importance",
    objective="mean",
    analyzer=None,
    progress=None,
    backend="auto",
    measures=False,
) -> OptimizationResult:
    """Optimise opacity, lighting and colour of ``spec`` for a readable rendering (Eq. 12-15).

    The volume is ray-analysed once per view (with the curvature volume); every evaluation
    then re-composites the cached rays (:func:`~dvr_perception.rays.engine.reevaluate`) and
    computes the three measures.  The stages run in the given order, each over its own
    parameters (:mod:`~dvr_perception.optimize.stages`), with conjugate gradients and annealing
    (:mod:`~dvr_perception.optimize._solver`; the opacity stage with SLSQP on exact ``E_v``
    and coverage gradients from the cached rays).  Evaluations use a camera whose long side is
    ``resolution`` pixels (default :data:`DEFAULT_RESOLUTION`, 96: "sampling the image"; an
    evaluation there costs a few hundredths of a second); the finite differences of the
    lighting and colour stages use one of :data:`FD_RESOLUTION` (48) pixels.  The result is
    then checked at the user's resolution: the last stages are undone until the objective
    (``E``, or ``S`` with ``objective="least_squares"``) has not risen and the re-checked
    guards (the opacity stage's coverage, within :data:`GUARD_SLACK`) hold, so
    ``final["E"] <= initial["E"]`` (with least squares ``final["S"] <= initial["S"]``).
    Only the initial and final terms are computed at the user's resolution (the stage
    records hold the optimisation resolution's terms).

    Parameters
    ----------
    volume : Volume
    spec : StructureSpec
        Importance, colours and lighting are the initial guess.
    camera : Camera
        The view (and the resolution of the reported measures and of ``region``).
    stages : sequence of str
        Names in :data:`~dvr_perception.optimize.stages.STAGES`, run in this order.
    weights : 3 numbers
        ``(w_v, w_s, w_t)`` of Eq. 12, >= 0 and not all zero.
    region : ndarray of bool (H, W), ("rect", x0, y0, x1, y1) or ("circle", cx, cy, r), optional
        The lens: only rays inside drive the objective, and only structures present there
        change (the light direction stays free).  See :mod:`~dvr_perception.optimize._region`.
    targets : dict, optional
        ``{structure: {"visibility": share, "transparency": perceived transparency}}``
        overriding the structure's target composition ``c`` where it is present (D1) and the
        expected opacity (``1 - transparency``).
    calibration : pair of array_like (x, y), optional
        Transparency calibration curve (:func:`~dvr_perception.measures.calibrate`).
    cameras : list of Camera, optional
        Further views: one parameter set is optimised for ``camera`` and these (terms averaged).
    seed : int
        Seed of the annealing moves; the same seed gives the same result.
    callback : callable, optional
        ``callback(intermediate_result)`` after every iteration with an
        :class:`~dvr_perception.optimize.results.IntermediateResult`; raise ``StopIteration``
        to stop (status 1, best parameters so far).
    max_iter : int
        Iterations per stage (CG steps and annealing moves).
    resolution : int, optional
        Long side of the optimisation camera (never above the user's).
    opacity_floor : float, optional
        Minimum mean accumulated opacity over the non-empty rays in the opacity stage
        (default: none; ``E_v`` itself penalises fading, decision D1).
    coverage_keep : float, optional
        The floor as a fraction of the starting coverage instead (default: none; e.g. 1
        forbids any fading); not together with ``opacity_floor``.
    allow_hue : bool
        Let the colour stage change hue (default: saturation and value only).
    curvature : ndarray, optional
        The curvature volume of ``volume`` and ``spec``
        (:func:`~dvr_perception.rays.curvature.curvature_volume`), when already computed
        (it does not depend on the optimised parameters; computed when not given).
    composition : {"importance", "thickness"}
        Target composition of ``E_v`` (:func:`~dvr_perception.measures.visibility`): each
        structure's share of a ray by importance and presence (default), or by thickness.
    objective : {"mean", "least_squares"}
        What every stage minimises (with its lead term's weight boosted) and what may never
        rise: ``"mean"``, the image-mean ``E = w_v E_v + w_s E_s + w_t E_t`` (Eq. 12), or
        ``"least_squares"``, Eq. 13's residue per pixel ``S = mean_r E(f, r)^2`` with
        ``E(f, r) = w_v d_v(r) + w_s d_s(r) + w_t d_t(r)`` over the rays that carry assigned
        opacity (mean over views).  Both ``E`` and ``S`` are reported either way.  The
        opacity stage's SLSQP minimises ``E_v`` in both modes; its candidates are judged on
        the objective.  The default is ``"mean"`` (decision D4, benchmark report section
        4b): on engine, cthead and lidc_chest at 512² both find (nearly) the same opacities
        (the opacity stage leads), so the images differ only through lighting and colour,
        and there the mean reveals as much or more: on the engine the least-squares run
        makes the inserts' face more saturated and solid, so what lies behind it shows a
        little less; cthead and lidc_chest look alike.  The mean is also cheaper (no full
        coarse evaluation per finite-difference gradient).
    analyzer : callable, optional
        ``analyzer(camera) -> RayAnalysis`` with a re-evaluation cache, instead of analysing
        ``volume`` (then ``None``) with ``curvature``: the MPI ranks' analysis, whose cache
        re-evaluates over the ranks (:meth:`~dvr_perception.distributed.RankSession.analyze`).
    progress : callable, optional
        The preparation's progress before the first iteration (the curvature volume and the
        views' ray analyses; :func:`~dvr_perception.rays.engine.analyze`'s ``progress``): a
        fraction in [0, 1], ending with 1.0; the iterations report through ``callback``.  A
        ``progress`` that raises :class:`StopIteration` cancels the optimisation with
        :class:`~dvr_perception.errors.DVRCancelled`.
    backend : {"auto", "numba", "numpy", "cuda"}
        Back end of the views' ray analyses (:func:`~dvr_perception.rays.engine.analyze`);
        the re-evaluations composite the cached rays on the CPU whatever the back end.
    measures : bool
        Also measure the first view at the user's resolution before and after
        (``all_measures(analysis, spec)`` with the measures' defaults; the result's
        ``measures``), each while what the measures share with the optimiser's own terms of
        that rendering is at hand (the start's right after its terms, the result's right
        after the final check): cheaper than measuring ``analyses`` afterwards, same numbers.

    Returns
    -------
    OptimizationResult

    Raises
    ------
    DVRInputError
        Bad weights, stage names, region, targets, calibration, objective or options.

    Examples
    --------
    >>> from dvr_perception.structures import make_phantom
    >>> vol, spec = make_phantom(size=32)
    >>> cam = Camera.from_view(vol.bounds, width=32, height=32)
    >>> res = optimize(vol, spec, cam, stages=("opacity",), max_iter=2)
    >>> res.final["E"] <= res.initial["E"], res.spec.structures[0].opacity is not None
    (True, True)
    """
    t_start = time.perf_counter()
    if backend not in BACKENDS:
        raise DVRInputError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    w = _check(volume, spec, camera, stages, weights, cameras, region, calibration, seed, callback,
               max_iter, resolution, opacity_floor, coverage_keep, analyzer)  # fmt: skip
    if composition not in COMPOSITIONS:
        raise DVRInputError(f"composition: expected one of {COMPOSITIONS}, got {composition!r}")
    if not isinstance(objective, str) or objective not in OBJECTIVES:
        raise DVRInputError(f"objective: expected one of {OBJECTIVES}, got {objective!r}")
    key = _KEY[objective]
    goals = parse_targets(targets, spec.names)
    mask = parse_region(region, camera.height, camera.width)
    views = [camera, *(cameras or [])]
    res = DEFAULT_RESOLUTION if resolution is None else int(resolution)
    smalls = [_reduced(cam, res) for cam in views]
    want_coarse = res >= 2 * FD_RESOLUTION and any(
        max(c.width, c.height) >= 2 * FD_RESOLUTION for c in smalls
    )
    coarse_cams = [_reduced(cam, FD_RESOLUTION) for cam in views] if want_coarse else []
    todo = [*views, *(s for s, cam in zip(smalls, views, strict=True) if s is not cam)]
    todo += coarse_cams
    prep = reporter(progress)
    if analyzer is None:
        if curvature is None:
            curvature = curvature_source(volume, spec, progress=prep.sub(0.0, 0.3))
        release_scratch(scratch=False)  # the heap that earlier work freed, before the peak
        # every camera in one call: a volume analysed in bricks is read once for all
        found = analyze_views(volume, spec, todo, curvature=curvature, progress=prep.sub(0.3, 1),
                              backend=backend, build_cache=True)  # fmt: skip
        release_scratch()  # no more caches are built here: the walk's scratch goes back
    else:
        found = [analyzer(cam) for cam in todo]
    prep(1.0)
    got = dict(zip(map(id, todo), found, strict=True))
    full_analyses = [got[id(cam)] for cam in views]
    opt_analyses = [got[id(s)] for s in smalls]
    opt_masks = [None if mask is None else resample_mask(mask, s.height, s.width) for s in smalls]
    full_masks = [mask] + [None] * (len(views) - 1)
    full_problem = Problem([a.cache for a in full_analyses], full_masks, spec, w, goals,
                           calibration, composition)  # fmt: skip
    full_problem.keep_transparency = measures  # measured again: its renderings' E_t kept
    same = all(a is b for a, b in zip(full_analyses, opt_analyses, strict=True))
    problem = full_problem
    if not same:
        caches = [a.cache for a in opt_analyses]
        problem = Problem(caches, opt_masks, spec, w, goals, calibration, composition)
    coarse = None
    if want_coarse:
        caches = [got[id(c)].cache for c in coarse_cams]
        masks = [None if mask is None else resample_mask(mask, c.height, c.width)
                 for c in coarse_cams]  # fmt: skip
        coarse = Problem(caches, masks, spec, w, goals, calibration, composition)

    params = Params.from_spec(spec)
    names = spec.names
    full0 = full_problem.terms(params, analyses=full_analyses)
    m_before = all_measures(full_analyses[0], spec) if measures else None
    initial = _report(full_problem, params, mask is not None, full0)
    terms = full0 if same else problem.terms(params, analyses=opt_analyses)
    active = problem.present()
    rng = np.random.default_rng(int(seed))
    done, nit, status, lum_ref = [], 0, 0, None
    for name in stages:
        stage = STAGES[name](allow_hue=allow_hue, opacity_floor=opacity_floor)
        if coverage_keep is not None:
            stage.coverage_keep = float(coverage_keep)
        if hasattr(stage, "protect"):
            stage.protect = _most_important(spec, active)
        if stage.brightened:
            lum_ref = terms if lum_ref is None else lum_ref
            stage.reference = lum_ref

        def notify(it, cur, best, _name=name):
            nonlocal nit
            nit += 1
            if callback is not None:
                callback(
                    IntermediateResult(
                        stage=_name,
                        iteration=it,
                        nit=nit,
                        nfev=problem.nfev
                        + (0 if same else full_problem.nfev)
                        + (0 if coarse is None else coarse.nfev),
                        terms=public_terms(cur.terms, names),
                        best_terms=public_terms(best.terms, names),
                        spec=cur.params.to_spec(spec),
                    )
                )

        best, snapshots, info = run_stage(
            stage, problem, params, terms, active, weights=w, rng=rng, max_iter=int(max_iter),
            notify=notify, coarse=coarse, verify=None if same else (full_problem, full0),
            objective=objective,
        )  # fmt: skip
        chosen = _pick(params, terms, best, snapshots, key)
        after = terms if chosen is None else chosen.terms
        done.append((stage, info, params, terms, chosen, after))
        params, terms = (params, terms) if chosen is None else (chosen.params, chosen.terms)
        if info["stopped"]:
            status = 1
            break
        if not info["converged"]:
            status = 2
    kept, params, final_terms, frac = _full_size_check(done, full0, full_problem, same, key)
    if params is None:
        params = Params.from_spec(spec)
    if frac is not None:  # record the shortened step as the stage's result
        stage, info, before, t_before, _, _ = done[kept - 1]
        t_opt = problem.terms(params)
        done[kept - 1] = (stage, info, before, t_before, _Shortened(params, t_opt, frac), t_opt)
    records = [_record(d, names, spec, i < kept) for i, d in enumerate(done)]
    final = _report(full_problem, params, mask is not None, final_terms)
    why = _why(problem, full_problem, Params.from_spec(spec), params, initial, final,
               done[:kept])  # fmt: skip
    nfev = problem.nfev + (0 if same else full_problem.nfev)
    nfev += 0 if coarse is None else coarse.nfev
    out_spec = params.to_spec(spec)
    last = full_problem.render(params, 0)
    kept_measures = () if not measures else (m_before, all_measures(last, out_spec))
    return OptimizationResult(
        spec=out_spec,
        initial=initial,
        final=final,
        stages=tuple(records),
        nit=nit,
        nfev=nfev,
        seconds=time.perf_counter() - t_start,
        status=status,
        message=STATUS_MESSAGES[status],
        success=status == 0,
        structures=why,
        analyses=(full_analyses[0], last),
        measures=kept_measures,
    )


def _why(problem, full_problem, start, params, initial, final, kept_stages) -> dict:
    """Per structure, what changed and why in words (:func:`~.explain.explain`).

    Who covers whom comes from the exact opacity gradients on the optimisation camera (mean
    of the start and the result); each structure's shape and transparency mismatch across
    the stage that leads that measure (the kept stages only) say why shading and colour
    changed.
    """
    changed = np.abs(params.opacities - start.opacities) >= 0.005
    covers = own = None
    if changed.any():
        model = OpacityModel(problem, start)
        (c0, own), (c1, _) = model.covering(start.opacities), model.covering(params.opacities)
        covers = 0.5 * (c0 + c1)
    bad = {}  # (stage lead, measure) -> per-structure mismatch before the first such stage, after
    for stage, _, _, t_before, chosen, t_after in kept_stages:
        if chosen is None or stage.lead not in ("E_s", "E_t"):
            continue
        for term in ("E_s", "E_t"):
            first = bad.get((stage.lead, term), (t_before["badness"][term], None))[0]
            bad[(stage.lead, term)] = (first, t_after["badness"][term])
    shape = bad.get(("E_s", "E_s"), (None, None))
    trans = bad.get(("E_t", "E_t"), (None, None))
    shape_c = bad.get(("E_t", "E_s"), (None, None))
    lighting = {
        "materials_before": start.lighting, "materials_after": params.lighting,
        "light_before": start.light, "light_after": params.light,
        "shape_before": shape[0], "shape_after": shape[1],
    }  # fmt: skip
    colour = {
        "colours_before": start.colours, "colours_after": params.colours,
        "transparency_before": trans[0], "transparency_after": trans[1],
        "shape_before": shape_c[0], "shape_after": shape_c[1],
    }  # fmt: skip
    return explain(problem.names, start.opacities, params.opacities, initial["visible_share"],
                   final["visible_share"], initial["target_share"], covers, lighting=lighting,
                   colour=colour, overlap=full_problem.copresence(), over=own)  # fmt: skip


def _most_important(spec, active) -> str | None:
    """Name of the most important structure the objective sees (first of equals)."""
    on = [s for s, a in zip(spec.structures, active, strict=True) if a]
    return max(on, key=lambda s: s.importance).name if on else None


def _holds(t, full0, done, k, key="E") -> bool:
    """``key`` (``E`` or ``S``) not above the start and the first ``k`` stages' guards held."""
    return t[key] <= full0[key] + 1e-12 and all(
        np.all(st.guards(t, full0, full=True) <= GUARD_SLACK) for st, *_ in done[:k] if st.recheck
    )


def _full_size_check(done, full0, full_problem, same, key="E"):
    """Run the hard check at the user's resolution: ``(kept, params, terms, fraction)``.

    Stages are undone from the last until ``key`` (``E``, or ``S`` for least squares) and the
    guards hold at full size; a stage
    whose whole step fails there is first retried with its step cut to each of
    :data:`SHORTER` (``fraction``; ``None`` for a whole step).  ``params`` is ``None`` when
    every stage is undone.
    """
    for kept in range(len(done), 0, -1):
        _, _, before, _, chosen, after = done[kept - 1]
        if chosen is None:
            continue
        t = after if same else full_problem.terms(chosen.params)
        if _holds(t, full0, done, kept, key):
            return kept, chosen.params, t, None
        for frac in () if same else SHORTER:
            p_short = before.toward(chosen.params, frac)
            t = full_problem.terms(p_short)
            if _holds(t, full0, done, kept, key) and t[key] < full0[key] - 1e-12:
                return kept, p_short, t, frac
    return 0, None, full0, None


def _pick(params, terms, best, snapshots, key="E"):
    """Return the newest best point of a stage whose ``key`` (E or S) has not risen (or None)."""
    for point in [best, *reversed(snapshots[-3:])]:
        if point.params is params or point.params.same(params):
            return None
        if point.terms[key] <= terms[key] + 1e-12:
            return point
    return None


class _Shortened:
    """A stage's step cut back to ``fraction`` of its length so that it holds at full size."""

    def __init__(self, params, terms, fraction):
        self.params, self.terms, self.fraction = params, terms, fraction


def _record(entry, names, spec, kept) -> StageRecord:
    stage, info, before, t_before, chosen, t_after = entry
    if chosen is None:
        message = "no feasible improvement found; parameters unchanged"
    elif kept and isinstance(chosen, _Shortened):
        message = (
            f"improved, with the step cut to {chosen.fraction:.0%} of its length "
            "(the whole step broke E or a guard at the user's resolution)"
        )
    elif kept:
        message = "improved"
    else:
        message = "undone: the objective (E or S) or a guard broken at the user's resolution"
    return StageRecord(
        name=stage.name,
        params_before=stage.describe(before, names),
        params_after=stage.describe(chosen.params if chosen is not None else before, names),
        terms_before=public_terms(t_before, names),
        terms_after=public_terms(t_after, names),
        iterations=info["iterations"],
        evaluations=info["evaluations"],
        seconds=info["seconds"],
        history=info["history"],
        converged=info["converged"],
        accepted=chosen is None or kept,
        message=message,
    )
