"""The per-stage solver: Polak-Ribiere conjugate gradients with annealing moves (Sec. 5).

The stage objective ``f(x) = F(x) + PENALTY * penalty(x)`` is minimised over the stage's
unbounded vector ``x`` (see :mod:`~dvr_perception.optimize.stages`), with ``w'`` the stage's
weights (the lead term boosted) and ``F`` either the image-mean ``w' . (E_v, E_s, E_t)``
(``objective="mean"``) or Eq. 13's least-squares residue per pixel, ``mean_r (w' . d(r))^2``
over the per-pixel deviations (``objective="least_squares"``,
:func:`~dvr_perception.optimize._problem.residue`).

**Opacity stage** (stages with ``exact = True``, :func:`_run_exact`): ``E_v`` and the coverage
and their exact gradients in the opacities come from :class:`~._exact.OpacityModel` (about a
millisecond at 96 px), so an iteration runs SLSQP (scipy; at most :data:`SLSQP_EVALS` model
evaluations each) from :data:`STARTS` points, minimising ``E_v`` in log-opacity subject to
``coverage >= floor +`` :data:`COVERAGE_MARGIN`: in the first iteration from the current point
and annealing moves of it, later from annealing moves only (log-opacities of structures chosen
as below, normal steps of :data:`HOP`; Metropolis acceptance of the iteration's result). When
the coverage at the user's resolution (one exact evaluation there, no gradient) misses its
floor, a result is moved up the coverage gradient until it holds (at most :data:`VERIFY`
doubling steps). The results get the full terms (one rendering each) in order of ``E_v`` until
one keeps the other terms' tolerances; the last one tried is moved halfway back towards the
current point when it breaks them (at most :data:`BACKTRACK` times, never below the coverage
floor).  SLSQP minimises the lead term ``E_v`` alone in both objectives (its exact gradient is
the cheap part); the candidate it returns is judged, accepted and kept on the stage objective
``f`` (least squares included) like any other point.

**Other stages** (conjugate gradients):

* **gradient**: forward finite differences with step :data:`FD_STEP` (0.01 in logit units)
  of the stage's cheap objective (only the measures in ``Stage.fast``; the others are held at
  the current point's values), on the ``coarse`` problem when given (the rays subsampled:
  :data:`~dvr_perception.optimize.core.FD_RESOLUTION`, 48 px).  With more than
  :data:`FULL_FD` parameters, one difference per parameter **group** (a structure's
  parameters, the light) along a seeded random +-1 direction within the group (simultaneous
  perturbation), so a gradient costs one evaluation per group instead of one per parameter;
* **direction**: Polak-Ribiere+ conjugate direction, preconditioned by the inverse fraction of
  rays on which each parameter's structure is present (small structures have small gradients),
  reset to steepest descent when it is not a descent direction, then bent so that every nearly
  active constraint improves (:func:`_feasible_direction`);
* **line search**: bounded backtracking (Armijo, ``c = 1e-4``) from a step that moves the largest
  entry by :data:`STEP` logit units, halved at most 6 times, doubled once if the first step
  already works; trial steps are judged on the cheap objective and only a passing one gets
  the remaining (expensive) measures, from the same rendering, before it is accepted;
* **annealing**: after :data:`CG_RUN` successful CG iterations or a failed line search, one
  simulated-annealing move (CG resumes after it unless it was rejected after a failed line
  search) perturbs the parameter groups (one per structure, plus the light)
  chosen at random; a group's move probability rises with its structure's deviation in the
  stage's lead term and with stalling (lead term improved less than 5 % since the stage
  start), as in the paper's last paragraph of Sec. 5.  Metropolis acceptance at a temperature
  that starts at ``0.05 f(x0)`` and cools by 0.7 per move.  Seeded by the caller's
  ``numpy.random.Generator``.

One **iteration** is one CG step or one annealing move.  The best *feasible* point (lowest
``(penalty, f)``) is kept, so a stage never returns something worse than its start.  A stage
has converged when :data:`PATIENCE` iterations in a row improve the best ``f`` by less than
:data:`FTOL` (relative).
"""

from __future__ import annotations

import copy
import itertools
import time
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from dvr_perception.optimize._exact import OpacityModel
from dvr_perception.optimize._problem import TERMS, public_terms, residue

__all__ = ["run_stage"]

FD_STEP = 1e-2
FULL_FD = 4  # up to this many parameters: one difference per parameter
PENALTY = 10.0
CG_RUN = 4
PATIENCE = 3
FTOL = 1e-3
SIGMA = 0.4  # annealing step (logit units)
STEP = 0.5  # first line-search step: largest parameter change in logit units
ACTIVE = 5e-3  # constraints closer than this to their bound steer the direction
ETA = 0.1
SLSQP_ITER = 30  # iterations of one SLSQP run of the opacity stage (exact gradients: cheap)
SLSQP_EVALS = 40  # evaluations of one SLSQP run (about 1 ms each at 96 px)
HOP = 0.8  # opacity stage annealing move: standard deviation in log-opacity
BACKTRACK = 3  # opacity stage: halvings towards the current point when a tolerance breaks
STARTS = 3  # opacity stage: SLSQP runs per iteration (the current point and annealing moves)
COVERAGE_MARGIN = 2e-3  # opacity stage: coverage kept this far above the floor (resolution)
VERIFY = 4  # opacity stage: steps up the coverage gradient until the user's floor holds
SHARE_MARGIN = 0.0  # opacity stage: guarded shares kept this far inside their bounds


@dataclass
class _Point:
    x: np.ndarray
    f: float
    pen: float
    terms: dict
    params: object
    smooth: float = 0.0
    cons: np.ndarray = None

    def key(self) -> tuple[float, float]:
        return (self.pen if self.pen > 1e-12 else 0.0, self.f)


class _Stopped(Exception):
    pass


class _Run:
    """State of one stage run (the closure over the problem, stage and counters)."""

    def __init__(self, stage, problem, params0, terms0, active, weights, rng, notify,
                 coarse=None, verify=None, objective="mean"):  # fmt: skip
        self.stage, self.problem, self.params0, self.active = stage, problem, params0, active
        self.coarse, self.verify = coarse, verify
        self.squares = objective == "least_squares"
        self.terms0, self.weights, self.rng, self.notify = terms0, weights, rng, notify
        self.w = stage.weights(weights)
        self.nfev = 0

    def point(self, x, params=None, terms=None, ref=None, problem=None) -> _Point:
        """Evaluate ``x``; with ``ref`` only ``stage.fast`` (the rest taken from ``ref``).

        ``problem`` (default: the stage's) evaluates the terms, e.g. the coarse one.
        """
        if params is None:
            params = self.stage.decode(self.params0, x, self.active)
        if terms is None:
            need = TERMS if ref is None else self.stage.fast
            terms = (problem or self.problem).terms(params, need=need)
            self.nfev += 1
            if ref is not None:
                held = [i for i, t in enumerate(TERMS) if t not in need]
                for i in held:
                    terms[TERMS[i]] = ref.terms[TERMS[i]]
                if self.squares:  # the held deviations of ref, per pixel (same rays)
                    terms["_stack"] = [s.copy() for s in terms["_stack"]]
                    for s, r in zip(terms["_stack"], ref.terms["_stack"], strict=True):
                        s[held] = r[held]
        cons = self.stage.constraints(terms, self.terms0, self.weights)
        pen = float(np.maximum(cons, 0.0).sum())
        if self.squares:
            smooth = residue(terms["_stack"], self.w)
        else:
            smooth = float(np.dot(self.w, [terms[t] for t in TERMS]))
        return _Point(np.array(x, float), smooth + PENALTY * pen, pen, terms, params, smooth, cons)

    def gradient(self, p: _Point, groups) -> tuple[np.ndarray, np.ndarray]:
        """Forward-difference gradient of the smooth objective and Jacobian of the constraints.

        One difference per parameter, or per group along a random +-1 direction when there
        are more than :data:`FULL_FD` parameters (see the module docstring).
        """
        g = np.zeros_like(p.x)
        jac = np.zeros((p.cons.size, p.x.size))
        if p.x.size <= FULL_FD:
            dirs = list(np.eye(p.x.size))
        else:
            sign = self.rng.choice([-1.0, 1.0], p.x.size)
            dirs = [np.where(groups == k, sign, 0.0) for k in np.unique(groups)]
        if self.coarse is not None:  # differences on the coarse rays: p again there first
            # (least squares: in full, the held deviations are needed per coarse pixel)
            ref = None if self.squares else p
            p = self.point(p.x, params=p.params, ref=ref, problem=self.coarse)
        for v in dirs:
            q = self.point(p.x + FD_STEP * v, ref=p, problem=self.coarse)
            g += v * (q.smooth - p.smooth) / FD_STEP
            jac += np.outer((q.cons - p.cons) / FD_STEP, v)
        return g, jac

    def full(self, q: _Point) -> _Point:
        """``q`` with every measure (``q`` itself when it has them)."""
        if "_analyses" not in q.terms:
            return q
        return self.point(q.x, params=q.params, terms=self.problem.complete(q.params, q.terms))

    def line_search(self, p: _Point, g: np.ndarray, d: np.ndarray) -> _Point | None:
        """Backtracking on the cheap objective; a passing step is then checked on all terms."""
        slope = float(g @ d)
        alpha = STEP / max(float(np.max(np.abs(d))), 1e-12)

        def ok(q, a):
            return q.f <= p.f + 1e-4 * a * slope and q.f < p.f and q.pen <= p.pen + 1e-12

        for tries in range(7):
            q = self.point(p.x + alpha * d, ref=p)
            if ok(q, alpha) and ok(q := self.full(q), alpha):
                if tries == 0:
                    r = self.point(p.x + 2.0 * alpha * d, ref=p)
                    if r.f < q.f and r.pen <= q.pen + 1e-12:
                        r = self.full(r)
                        if r.f < q.f and r.pen <= q.pen + 1e-12:
                            return r
                return q
            alpha *= 0.5
        return None

    def anneal(self, p: _Point, groups, group_structures, temperature, stalled) -> _Point:
        bad = np.array(
            [
                0.0 if s is None else float(p.terms["badness"][self.stage.lead][s])
                for s in group_structures
            ]
        )
        top = bad.max() if bad.size else 0.0
        prob = 0.25 + (0.5 * bad / top if top > 0 else 0.25) + (0.2 if stalled else 0.0)
        prob = np.clip(prob, 0.05, 0.95)
        chosen = self.rng.random(prob.size) < prob
        if not chosen.any():
            chosen[int(np.argmax(prob))] = True
        step = self.rng.normal(0.0, SIGMA, p.x.size) * chosen[groups]
        q = self.point(p.x + step)
        u = self.rng.random()
        if q.key() <= p.key() or (
            q.pen <= p.pen + 1e-12 and u < np.exp(-(q.f - p.f) / max(temperature, 1e-12))
        ):
            return q
        return p


def _feasible_direction(d0, cons, jac):
    """Closest direction to ``d0`` that improves every nearly active constraint.

    Constraints with ``c > -ACTIVE`` must satisfy ``a . d <= -ETA |a| |d0|`` (move strictly
    inwards, so that curvature does not carry the step out); solved by enumerating the active
    sets of this tiny projection problem.  Returns ``None`` when no such direction exists.
    """
    near = cons > -ACTIVE
    a = jac[near]
    if a.shape[0] == 0:
        return d0
    scale = np.linalg.norm(d0)
    b = -ETA * np.linalg.norm(a, axis=1) * scale
    if np.all(a @ d0 <= b):
        return d0
    best = None
    for size in range(1, a.shape[0] + 1):
        for subset in itertools.combinations(range(a.shape[0]), size):
            rows = a[list(subset)]
            gram = rows @ rows.T + 1e-12 * np.eye(size)
            lam = np.linalg.solve(gram, rows @ d0 - b[list(subset)])
            if np.any(lam < 0):
                continue
            d = d0 - rows.T @ lam
            if np.all(a @ d <= b + 1e-9 * scale) and (
                best is None or np.linalg.norm(d - d0) < np.linalg.norm(best - d0)
            ):
                best = d
    if best is None or not np.any(best):
        return None
    return best


def _run_exact(run, x0, groups, group_structures, max_iter, info, history):
    """Run the opacity stage: SLSQP on exact ``E_v`` and coverage, with annealing restarts.

    See :func:`run_stage` and the module docstring.  Returns ``(best, snapshots)``.
    """
    stage, problem, params0 = run.stage, run.problem, run.params0
    model = OpacityModel(problem, params0)
    idx = np.flatnonzero(run.active)
    ops0 = np.clip(params0.opacities, *stage.bounds)
    lo, hi = np.log(stage.bounds[0]), np.log(stage.bounds[1])
    bound = [stage.floor(run.terms0) + COVERAGE_MARGIN]
    # share bounds (D6): the structures below their target share only move toward it
    bounds = stage.share_bounds(run.terms0) if hasattr(stage, "share_bounds") else {}
    guarded = np.array([problem.names.index(n) for n in bounds], np.int64)
    share_lo = np.array([b[0] for b in bounds.values()], float) + SHARE_MARGIN
    share_hi = np.array([min(b[1], 2.0) for b in bounds.values()], float) - SHARE_MARGIN
    user = None
    if run.verify is not None:  # the coverage at the user's resolution, exactly
        user = (OpacityModel(run.verify[0], params0), stage.floor(run.verify[1]))
    memo = {}

    def cheap(y, grad=False):
        """``(E_v, coverage, dE_v, dcoverage, share slack, dslack)`` at ``y``, remembered.

        The gradients (``None`` until asked for with ``grad``) are computed on demand: SLSQP
        asks for values alone at its line-search points.  A point counts as one model
        evaluation (:data:`SLSQP_EVALS`) whether or not its gradients are asked for.
        """
        key = np.asarray(y, float).tobytes()
        hit = memo.get(key)
        if hit is None or (grad and hit[2] is None):
            ops = ops0.copy()
            ops[idx] = np.exp(np.clip(y, lo, hi))
            e_v, cov, g_v, g_c, share, d_share = model.evaluate(ops, grad=grad, shares=True)
            if hit is not None:  # the gradients of a point already counted
                model.nfev -= 1
            jac = np.exp(np.clip(y, lo, hi))
            s, ds = share[guarded], d_share[guarded][:, idx] * jac
            slack = np.concatenate([s - share_lo, share_hi - s])
            if not grad:
                memo[key] = (e_v, cov, None, None, slack, None)
            else:
                memo[key] = (e_v, cov, g_v[idx] * jac, g_c[idx] * jac, slack,
                             np.concatenate([ds, -ds]))  # fmt: skip
        return memo[key]

    class _Budget(Exception):
        pass

    def local(y_from):
        """SLSQP from ``y_from``: minimise ``E_v`` subject to coverage >= floor.

        Returns the evaluated point with the lowest ``E_v`` that meets the floor (SLSQP's
        last iterate may not), or ``None``; at most :data:`SLSQP_EVALS` new evaluations.
        """
        found, n0, floor = [None, np.inf], model.nfev, bound[0]

        def value(y):
            if model.nfev - n0 >= SLSQP_EVALS:
                raise _Budget
            e_v, cov, _, _, slack, _ = cheap(y)
            if cov >= floor and np.all(slack >= 0.0) and e_v < found[1]:
                found[:] = [np.clip(np.array(y, float), lo, hi), e_v]
            return e_v

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                minimize(
                    value, y_from, jac=lambda y: cheap(y, True)[2], method="SLSQP",
                    bounds=[(lo, hi)] * idx.size,
                    constraints=[{"type": "ineq", "fun": lambda y: cheap(y)[1] - floor,
                                  "jac": lambda y: cheap(y, True)[3]}]
                    + ([{"type": "ineq", "fun": lambda y: cheap(y)[4],
                         "jac": lambda y: cheap(y, True)[5]}] if guarded.size else []),
                    options={"maxiter": SLSQP_ITER, "ftol": 1e-5},
                )  # fmt: skip
        except _Budget:
            pass
        return found[0]

    def user_shortfall(y):
        """How far the coverage at the user's resolution is below its floor (<= 0: fine)."""
        if user is None:
            return 0.0
        ops = ops0.copy()
        ops[idx] = np.exp(np.clip(y, lo, hi))
        return user[1] - user[0].coverage(ops)

    def verified(y_from):
        """:func:`local`, then moved up the coverage gradient until the user's floor holds.

        The step along the (optimisation resolution's) coverage gradient starts at the
        linear estimate of the shortfall and doubles, at most :data:`VERIFY` times.
        """
        y = local(y_from)
        if y is None:
            return None
        short = user_shortfall(y)
        if short <= 0.0:
            return y
        d = cheap(y, True)[3]
        if not np.any(d > 0):
            return None
        t = 1.5 * short / float(d @ d)
        for _ in range(VERIFY):
            z = np.clip(y + t * d, lo, hi)
            if user_shortfall(z) <= 0.0:
                return z
            t *= 2.0
        return None

    def full(y):
        ops = params0.opacities.copy()
        ops[idx] = np.exp(y)
        params = params0.replace(opacities=ops)
        return run.point(stage.encode(params, run.active)[0], params=params)

    start = run.point(x0, params=params0, terms=run.terms0)
    y_best = y_cur = np.log(ops0[idx])
    best, cur, snapshots, quiet = start, start, [], 0
    temperature = 0.05 * max(abs(start.f), 1e-2)
    for it in range(1, max_iter + 1):
        prev_best = best.f
        froms = [y_cur] if it == 1 else []
        kind = "slsqp" if it == 1 else "anneal"
        bad = np.array([float(cur.terms["badness"][stage.lead][s]) for s in idx])
        top = bad.max() if bad.size else 0.0
        prob = np.clip(0.25 + (0.5 * bad / top if top > 0 else 0.25), 0.05, 0.95)
        while len(froms) < STARTS:  # annealing moves: more likely where E_v deviates most
            chosen = run.rng.random(idx.size) < prob
            if not chosen.any():
                chosen[int(np.argmax(prob))] = True
            froms.append(np.clip(y_cur + run.rng.normal(0.0, HOP, idx.size) * chosen, lo, hi))
        found = [y for y in map(verified, froms) if y is not None]
        found.sort(key=lambda y: cheap(y)[0])
        new = None
        for n_try, y_try in enumerate(found[:STARTS]):  # the lowest E_v that keeps tolerances
            for _ in range(BACKTRACK + 1 if n_try == len(found[:STARTS]) - 1 else 1):
                q = full(y_try)
                if q.pen <= 1e-12:
                    new = q
                    break
                y_try = 0.5 * (y_try + y_cur)  # the last candidate: back towards y_cur
                if cheap(y_try)[1] < bound[0] or user_shortfall(y_try) > 0.0:
                    break
            if new is not None:
                break
        u = run.rng.random()
        if new is not None and (
            new.key() <= cur.key() or u < np.exp(-(new.f - cur.f) / max(temperature, 1e-12))
        ):
            cur, y_cur = new, np.log(new.params.opacities[idx])
        else:
            kind += " (rejected)"
        temperature *= 0.7
        if cur.key() < best.key():
            snapshots.append(best)
            best, y_best = cur, y_cur
        elif it > 1 and best is not cur:  # restart the hops from the best point
            cur, y_cur = best, y_best
        quiet = quiet + 1 if prev_best - best.f < FTOL * max(abs(prev_best), 1e-3) else 0
        entry = public_terms(cur.terms, problem.names)
        entry.update(iteration=it, kind=kind, f=cur.f, penalty=cur.pen, best_f=best.f)
        history.append(entry)
        info["iterations"] = it
        try:
            run.notify(it, cur, best)
        except StopIteration:
            info["stopped"] = True
            break
        if quiet >= PATIENCE:
            info["converged"] = True
            break
    run.nfev += model.nfev + (0 if user is None else user[0].nfev)
    info["exact_evaluations"] = model.nfev + (0 if user is None else user[0].nfev)
    return best, snapshots


def run_stage(stage, problem, params0, terms0, active, *, weights, rng, max_iter, notify,
              coarse=None, verify=None, objective="mean"):  # fmt: skip
    """Optimise ``stage``'s parameters from ``params0`` (terms ``terms0``).

    ``objective``: ``"mean"`` (the weighted image means) or ``"least_squares"`` (Eq. 13 per
    pixel, see the module docstring) as the stage's smooth objective.
    ``coarse``: a :class:`~._problem.Problem` of the same views on fewer rays, for the
    finite differences of the gradient (``None``: ``problem``).  ``verify``: ``(problem,
    terms)`` at the user's resolution, where the opacity stage checks its coverage floor
    (``None``: ``problem`` is at the user's resolution).

    ``notify(iteration, current _Point, best _Point)`` is called after every iteration; it may
    raise ``StopIteration`` to stop.  Returns ``(best, snapshots, info)``: the best feasible
    point, the earlier best points (oldest first) and a dict with ``iterations``,
    ``evaluations``, ``seconds``, ``history``, ``converged``, ``stopped``.
    """
    t0 = time.perf_counter()
    run = _Run(stage, problem, params0, terms0, active, weights, rng, notify, coarse, verify,
               objective)  # fmt: skip
    x0, groups, group_structures = stage.encode(params0, active)
    frac = problem.presence_fraction()
    share = np.array([1.0 if s is None else max(frac[s], 0.01) for s in group_structures])
    precond = 1.0 / share[groups] if x0.size else np.ones(0)
    start = run.point(x0, params=params0, terms=terms0)
    best, snapshots, history = start, [], []
    info = {"iterations": 0, "converged": x0.size == 0, "stopped": False}
    if x0.size and getattr(stage, "exact", False):
        best, snapshots = _run_exact(run, x0, groups, group_structures, max_iter, info, history)
    elif x0.size:
        cur, d, g_prev, z_prev, mode, run_len, quiet = start, None, None, None, "cg", 0, 0
        stuck = False  # the line search failed at ``cur``: only annealing can move on
        temperature = 0.05 * max(abs(start.f), 1e-2)
        lead0 = terms0[stage.lead]
        for it in range(1, max_iter + 1):
            prev_best = best.f
            if mode == "cg":
                g, jac = run.gradient(cur, groups)
                z = precond * g
                if d is None or g_prev is None:
                    d = -z
                else:
                    beta = max(0.0, float(z @ (g - g_prev)) / max(float(z_prev @ g_prev), 1e-30))
                    d = -z + beta * d
                if float(g @ d) >= 0:
                    d = -z
                d = _feasible_direction(d, cur.cons, jac)
                new = None if d is None else run.line_search(cur, g, d)
                kind = "cg"
                if new is None:
                    mode, d, g_prev, stuck = "anneal", None, None, True
                else:
                    cur, g_prev, z_prev, run_len = new, g, z, run_len + 1
                    if run_len >= CG_RUN:
                        mode = "anneal"
            else:
                stalled = cur.terms[stage.lead] > 0.95 * lead0
                new = run.anneal(cur, groups, group_structures, temperature, stalled)
                kind = "anneal" + ("" if new is not cur else " (rejected)")
                temperature *= 0.7
                if new is not cur or not stuck:
                    mode, d, g_prev, run_len, stuck = "cg", None, None, 0, False
                cur = new
            if cur.key() < best.key():
                if best.pen == 0.0 or best is start:
                    snapshots.append(best)
                best = cur
            quiet = quiet + 1 if prev_best - best.f < FTOL * max(abs(prev_best), 1e-3) else 0
            entry = public_terms(cur.terms, problem.names)
            entry.update(iteration=it, kind=kind, f=cur.f, penalty=cur.pen, best_f=best.f)
            history.append(entry)
            info["iterations"] = it
            try:
                notify(it, cur, best)
            except StopIteration:
                info["stopped"] = True
                break
            if quiet >= PATIENCE:
                info["converged"] = True
                break
    info.update(
        evaluations=run.nfev,
        seconds=time.perf_counter() - t0,
        history=tuple(copy.deepcopy(history)),
    )
    return best, snapshots, info
