"""Exact ``E_v`` and coverage, with their gradients in the opacities, from cached rays.

The opacity stage needs only the visibility term ``E_v`` (visible against the fixed target
opacities, decision D1) and the coverage (mean accumulated opacity) for most of its
evaluations; both depend on the per-structure rendering opacities only through the front-to-back
compositing of each ray's cached samples.  :class:`OpacityModel`
re-composites the :class:`~dvr_perception.rays.engine.RayCache` entries itself (no colour, no
shading: a few milliseconds) and differentiates the compositing analytically: along a ray,
with ``T_e`` the transmittance before entry ``e`` (structure ``s_e``, step-corrected opacity
``a_e``),

* ``visible_j = sum_{e: s_e = j} a_e T_e`` and ``acc = 1 - prod_e (1 - a_e)``;
* ``d log T_e / d o_k = - sum_{e' < e, s_e' = k} (d a_e' / d o_k) / (1 - a_e')``, kept as a
  running sum ``G_k`` per structure, so ``d visible_j / d o_k`` accumulates
  ``a_e T_e G_k`` (plus ``T_e d a_e / d o_k`` when ``j = k``) in one pass.

Values use the engine's quantised opacity table (:func:`~dvr_perception.rays._tables.alpha_table`)
and its early ray termination, so they equal the ``E_v`` and ``coverage`` of
:class:`~dvr_perception.optimize._problem.Problem` up to float rounding; the derivative of
``a = 1 - (1 - o m) ** ratio`` is taken without the 1/32767 rounding.
"""

from __future__ import annotations

import types

import numpy as np

from dvr_perception.rays import _tables

try:
    from numba import njit, prange
except ImportError:  # no numba: the same loop in plain Python (slow, same numbers)
    prange = range

    def njit(*args, **_kwargs):
        """Stand-in for :func:`numba.njit` that returns the function unchanged."""
        return args[0] if args and callable(args[0]) else (lambda f: f)


__all__ = ["OpacityModel"]

#: From this many selected rays on, the rays are composited on all threads
#: (:func:`_composite_grad_parallel`; every ray's numbers are the same either way).
PARALLEL_RAYS = 4096
#: Rays per block of :func:`_composite_grad_body` (one scratch per block).
BLOCK = 64


def _composite_grad_body(rays, start, count, lut, ids, alpha, dalpha, dlog, k, ert, grad, vis,
                         dvis, acc, dacc):  # fmt: skip
    """Per selected ray: visible opacity per structure, accumulated opacity, and gradients.

    Without ``grad`` only ``vis`` and ``acc`` are written (``dvis`` and ``dacc`` are not
    touched and may be any arrays of the right dimensions).  Compiled twice: serial
    (:func:`_composite_grad`, few rays) and over the rays in parallel
    (:func:`_composite_grad_parallel`); each ray is independent of the others, so both give
    the same numbers.  ``dlog`` is :func:`log_step`'s ``d log(1 - a) / d o`` per table entry
    (``dalpha / max(1 - alpha, 1e-9)``, the quotient the loop would take per sample).  The
    rays go in blocks of :data:`BLOCK`: each block has its scratch
    (the running ``G``, one ray's ``visible`` and ``d visible``), so a ray's sums stay in a few
    cache lines and are written out once, with the same operations in the same order.
    ``G_q`` is 0 until structure ``q`` is met on the ray, and adding ``w * 0`` to a
    derivative that only ever had such terms leaves it 0: only the structures met so far are
    visited (the same numbers, fewer operations).
    """
    n = rays.shape[0]
    nblock = (n + BLOCK - 1) // BLOCK
    for b in prange(nblock):
        g = np.empty(k)
        lv = np.empty(k)
        ld = np.empty(k * k if grad else 1)
        met = np.empty(k, np.int64)  # the structures met so far on the ray, in order
        seen = np.empty(k, np.bool_)
        for i in range(b * BLOCK, min((b + 1) * BLOCK, n)):
            r = rays[i]
            tr = 1.0
            m = 0
            for s in range(k):
                g[s] = 0.0
                lv[s] = 0.0
                seen[s] = False
            if grad:
                for q in range(k * k):
                    ld[q] = 0.0
            for e in range(start[r], start[r] + count[r]):
                idx = lut[e]
                al = alpha[idx]
                if al <= 0.0:
                    continue
                s = ids[idx]
                w = al * tr
                lv[s] += w
                if grad:
                    if not seen[s]:
                        seen[s] = True
                        met[m] = s
                        m += 1
                    row = s * k
                    for qi in range(m):  # G is 0 for a structure not met yet: nothing to add
                        q = met[qi]
                        ld[row + q] += w * g[q]
                    ld[row + s] += dalpha[idx] * tr
                    g[s] -= dlog[idx]
                tr *= 1.0 - al
                if tr < ert:
                    break
            acc[i] = 1.0 - tr
            for s in range(k):
                vis[s, i] = lv[s]
            if grad:
                for s in range(k):
                    for q in range(k):
                        dvis[s, q, i] = ld[s * k + q]
                for q in range(k):
                    dacc[q, i] = -tr * g[q]


def _compiled(name: str, parallel: bool):
    """:func:`_composite_grad_body` compiled (cached) under its own name ``name``.

    numba's on-disk cache keys a kernel by its Python function (module, qualified name, first
    line) and signature, not by the compile options: one function compiled twice, serial and
    ``parallel=True``, shares one cache entry, and whichever was compiled first is what both
    load afterwards.  Each variant is therefore a function of its own (the same code).
    """
    body = _composite_grad_body
    func = types.FunctionType(body.__code__, body.__globals__, name, body.__defaults__,
                              body.__closure__)  # fmt: skip
    func.__qualname__ = name
    func.__doc__ = body.__doc__
    return njit(parallel=parallel, cache=True)(func)


_composite_grad = _compiled("_composite_grad", parallel=False)
_composite_grad_parallel = _compiled("_composite_grad_parallel", parallel=True)


def composite_grad(rays, *args) -> None:
    """Run :func:`_composite_grad_body`: serial below :data:`PARALLEL_RAYS` rays, else parallel."""
    kernel = _composite_grad if rays.shape[0] < PARALLEL_RAYS else _composite_grad_parallel
    kernel(rays, *args)


@njit(cache=True)
def composite_grad_part(rays, start, count, lut, ids, alpha, dalpha, k, ert, grad, tr, g, vis,
                        dvis):  # fmt: skip
    """:func:`_composite_grad` over one brick's entries, continuing each selected ray's state.

    Per selected ray ``i``: ``tr[i]`` the transmittance, ``g[:, i]`` the running
    ``d log T / d o``, ``vis[:, i]`` and (with ``grad``) ``dvis[:, :, i]``, all updated in place
    with the same operations as :func:`_composite_grad`; a ray already below ``ert`` is left
    as it is.  Walking the bricks in view order from ``tr = 1`` and zeros gives the whole
    ray's values bit for bit; then ``acc = 1 - tr`` and ``dacc = -tr * g``.
    """
    for i in range(rays.shape[0]):
        r = rays[i]
        t = tr[i]
        if t < ert:
            continue
        for e in range(start[r], start[r] + count[r]):
            idx = lut[e]
            al = alpha[idx]
            if al <= 0.0:
                continue
            s = ids[idx]
            w = al * t
            vis[s, i] += w
            if grad:
                for q in range(k):
                    dvis[s, q, i] += w * g[q, i]
                da = dalpha[idx]
                dvis[s, s, i] += da * t
                g[s, i] -= da / max(1.0 - al, 1e-9)
            t *= 1.0 - al
            if t < ert:
                break
        tr[i] = t


def log_step(alpha, dalpha) -> np.ndarray:
    """Per table entry, ``-d log(1 - a) / d o = dalpha / max(1 - alpha, 1e-9)`` (float64).

    What :func:`composite_grad_part` computes per sample (the same IEEE quotient), once per
    entry for :func:`_composite_grad_body`.
    """
    return dalpha / np.maximum(1.0 - alpha, 1e-9)


def opacity_tables(ids, membership, ratio, ops) -> tuple:
    """Return ``(alpha, dalpha, structure)`` per table entry at opacities ``ops`` (K,).

    The engine's quantised step-corrected opacity, its derivative in the structure's opacity
    (without the rounding) and the structure index (0 outside every structure, where the
    opacity is 0).
    """
    alpha = _tables.alpha_table(ids, membership, ops, ratio)
    ids = np.asarray(ids)
    m = np.asarray(membership, np.float64)
    o = _tables.entry_opacity(ids, m, ops)
    base = np.clip(1.0 - o, 1e-9, 1.0)
    da = np.where(o > 1e-4, ratio * m * base ** (ratio - 1.0), m)
    return alpha, np.where(ids >= 0, da, 0.0), np.maximum(ids, 0).astype(np.int64)


class OpacityModel:
    """``E_v`` and coverage of one problem as functions of the K rendering opacities.

    Parameters
    ----------
    problem : Problem
        Its caches, masks and (targets-adjusted) target opacities define the terms.
    params : Params
        Any parameter set (used once per view to set up the problem's fixed parts).
    """

    def __init__(self, problem, params) -> None:
        self.views = []
        for v, cache in enumerate(problem.caches):
            fixed = problem.fixed_parts(v, params)
            rays = np.flatnonzero(fixed["rays"].ravel()).astype(np.int64)
            self.views.append((cache, rays, np.asarray(fixed["target"], np.float64)))
        self.k = len(problem.names)
        self.nfev = 0

    def _tables(self, cache, ops):
        return opacity_tables(cache.ids, cache.membership, cache.ratio, ops)

    def evaluate(self, ops, grad: bool = True, shares: bool = False) -> tuple:
        """Return ``(E_v, coverage, dE_v/do, dcoverage/do)`` at opacities ``ops`` (K,).

        With ``grad=False`` the two gradients are zeros (and not computed).  With
        ``shares=True`` two more entries follow: each structure's share of the picture
        (``sum_r visible_s / sum_r sum_s' visible_s'``, (K,), mean over the views, as the
        problem's ``visible_share``) and its Jacobian in the opacities ((K, K); zeros
        without ``grad``).
        """
        self.nfev += 1
        ops = np.clip(np.asarray(ops, np.float64), 0.0, 1.0)
        k = self.k
        e_v = cov = 0.0
        g_v, g_c = np.zeros(k), np.zeros(k)
        share, d_share = np.zeros(k), np.zeros((k, k))
        for cache, rays, target in self.views:
            n = rays.size
            if n == 0:
                continue
            vis, dvis, acc, dacc = self._pass(cache, rays, ops, grad)
            acc32, vis32 = acc.astype(np.float32), vis.astype(np.float32)  # as the engine's
            diff = target - vis32.astype(np.float64)
            e_v += float(np.abs(diff).sum(axis=0).mean())
            cov += float(acc32.mean())
            v_sum = vis32.astype(np.float64).sum(axis=1)
            total = float(v_sum.sum())
            if total > 0:
                share += v_sum / total
            if not grad:
                continue
            if total > 0:  # d (V_s / V) / d o_q = (dV_sq V - V_s dV_q) / V^2
                dv = dvis.sum(axis=2)
                d_share += (dv * total - v_sum[:, None] * dv.sum(axis=0)[None, :]) / total**2
            # alpha_v = visible (D1): d delta_v / d o_q = -sum_j sign(diff_j) d visible_j / d o_q
            sgn = -np.sign(diff)
            g_v += (sgn[:, None, :] * dvis).sum(axis=(0, 2)) / n
            g_c += dacc.sum(axis=1) / n
        nv = len(self.views)
        out = (e_v / nv, cov / nv, g_v / nv, g_c / nv)
        return (*out, share / nv, d_share / nv) if shares else out

    def coverage(self, ops) -> float:
        """Return the coverage at opacities ``ops`` (K,): ``evaluate(ops, grad=False)[1]``.

        The same compositing and the same float32 mean, without ``E_v`` and the shares (the
        opacity stage's check at the user's resolution needs only this).  Counts as one
        evaluation.
        """
        self.nfev += 1
        ops = np.clip(np.asarray(ops, np.float64), 0.0, 1.0)
        cov = 0.0
        for cache, rays, _ in self.views:
            if rays.size == 0:
                continue
            acc = self._pass(cache, rays, ops, False)[2]
            cov += float(acc.astype(np.float32).mean())
        return cov / len(self.views)

    def _pass(self, cache, rays, ops, grad: bool) -> tuple:
        """``(visible, d visible, accumulated, d accumulated)`` of one view's ``rays`` at ``ops``.

        The derivatives (in the opacities) are zeros of one column without ``grad``.
        """
        if hasattr(cache, "opacity_pass"):  # entries spread over MPI ranks
            return cache.opacity_pass(rays, ops, grad)
        k, n = self.k, rays.size
        alpha, dalpha, ids = self._tables(cache, ops)
        vis, acc = np.empty((k, n)), np.empty(n)
        if grad:  # the kernel writes every ray's derivatives
            dvis, dacc = np.empty((k, k, n)), np.empty((k, n))
        else:
            dvis, dacc = np.zeros((k, k, 1)), np.zeros((k, 1))
        composite_grad(rays, cache.start, cache.count, cache.lut, ids, alpha, dalpha,
                       log_step(alpha, dalpha), k, _tables.ERT, grad, vis, dvis, acc,
                       dacc)  # fmt: skip
        return vis, dvis, acc, dacc

    def covering(self, ops) -> tuple:
        """Who hides whom, and who shows more than its target, at opacities ``ops``.

        Returns ``(covers, own)``.  ``covers`` (K, K): entry ``[k, j]`` is
        ``-sum_r d visible_j / d o_k`` over the counted rays divided by the picture's visible
        opacity ``sum_r sum_s visible_s`` (mean over the views): to first order, the share of
        the picture ``j`` gains per unit that ``k``'s opacity falls.  Only a structure in
        front hides one behind (a sample lowers the transmittance of those after it), so a
        structure that lies wholly behind another covers it by 0; diagonal 0, never negative.
        ``own`` (K,): ``sum_r sign(visible_k - target_k) d visible_k / d o_k``, normalised
        the same way: positive when, where the structure shows, its visible opacity is mostly
        above its target opacity (so lowering it brings its own rays closer to the target).
        """
        ops = np.clip(np.asarray(ops, np.float64), 0.0, 1.0)
        k = self.k
        out, own = np.zeros((k, k)), np.zeros(k)
        for cache, rays, target in self.views:
            n = rays.size
            if n == 0:
                continue
            if hasattr(cache, "opacity_pass"):
                vis, dvis, _, _ = cache.opacity_pass(rays, ops, True)
            else:
                alpha, dalpha, ids = self._tables(cache, ops)
                vis, acc = np.empty((k, n)), np.empty(n)
                dvis, dacc = np.zeros((k, k, n)), np.zeros((k, n))
                composite_grad(rays, cache.start, cache.count, cache.lut, ids, alpha, dalpha,
                               log_step(alpha, dalpha), k, _tables.ERT, True, vis, dvis, acc,
                               dacc)  # fmt: skip
            vis = np.asarray(vis, np.float64)
            dvis = np.asarray(dvis, np.float64)
            total = float(vis.sum())
            if total > 0:
                out -= dvis.sum(axis=2).T / total  # dvis[s, q]: d vis_s / d o_q
                self_d = dvis[np.arange(k), np.arange(k)]  # (K, rays)
                sign = np.sign(vis.astype(np.float32).astype(np.float64) - target)
                own += (sign * self_d).sum(axis=1) / total
        nv = max(len(self.views), 1)
        out /= nv
        np.fill_diagonal(out, 0.0)
        return np.clip(out, 0.0, None), own / nv
