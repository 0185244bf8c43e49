"""Pure-numpy back end of the ray-analysis engine (used when numba is unavailable).

Same sample positions, table lookups, normal quantisation and compositing as
:mod:`dvr_perception.rays._numba_kernels`, vectorised over all rays that are still inside the
volume at each step.  It does no empty-space skipping (skipping never changes results) and
always builds the cache entries, then composites them with :func:`composite`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["composite", "walk"]

_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0
_CORNERS = [((c & 1), (c >> 1) & 1, c >> 2) for c in range(8)]


def _shade(q, s, light, stab) -> tuple[np.ndarray, np.ndarray]:
    """Diffuse factor and specular term per entry (see the numba ``_shade``)."""
    n = q.astype(np.float64) / 127.0
    ndl = n[:, 0] * light[4, 0] + n[:, 1] * light[4, 1] + n[:, 2] * light[4, 2]
    ndh = n[:, 0] * light[5, 0] + n[:, 1] * light[5, 1] + n[:, 2] * light[5, 2]
    lit = ndl > 0.0
    dfac = light[0, s] + np.where(lit, light[1, s] * ndl, 0.0)
    u = np.clip(ndh, 0.0, 1.0) * (stab.shape[1] - 1)
    i = np.minimum(u.astype(np.int64), stab.shape[1] - 2)
    spec = stab[s, i] + (u - i) * (stab[s, i + 1] - stab[s, i])
    spec = np.where(lit & (ndh > 0.001), spec, 0.0)
    return dfac, spec


def walk(idx, nrm, curv, seg, step, ids, memb, alpha_w, light, shade, has_curv, k_count):
    """March all rays; return cache entries in ray order plus ``present`` and ``assigned``.

    Returns a dict with ``off`` (R+1 int64), ``lut`` (uint16), ``nrm`` (int8 (E, 3)),
    ``curv`` (float32), ``present`` (uint32 R), ``assigned`` (float64 (K, R)).
    """
    a, b, t_first, n = seg["a"], seg["b"], seg["t"], seg["n"]
    nrays = len(n)
    nz, ny, nx = idx.shape
    present = np.zeros(nrays, np.uint32)
    assigned = np.zeros((k_count, nrays))
    order = np.argsort(-n.astype(np.int64), kind="stable")
    neg = -n[order].astype(np.int64)
    parts: dict[str, list] = {"ray": [], "lut": [], "nrm": [], "curv": []}
    view = light[6, :3]
    for j in range(int(-neg[0]) if nrays else 0):
        rr = order[: np.searchsorted(neg, -j, side="left")]
        t = t_first[rr] + j * step
        p = a[rr] + t[:, None] * b[rr]
        cell = np.minimum(np.maximum(p.astype(np.int64), 0), np.array([nx, ny, nz]) - 2)
        frac = np.clip(p - cell, 0.0, 1.0)
        x, y, z = cell[:, 0], cell[:, 1], cell[:, 2]
        weights = []
        f = np.zeros(len(rr))
        for dx, dy, dz in _CORNERS:
            w = (
                (frac[:, 0] if dx else 1.0 - frac[:, 0])
                * (frac[:, 1] if dy else 1.0 - frac[:, 1])
                * (frac[:, 2] if dz else 1.0 - frac[:, 2])
            )
            weights.append(w)
            f += w * idx[z + dz, y + dy, x + dx]
        k = np.minimum((f * _W_SCALE + _W_BIAS).astype(np.int64), len(ids) - 1)
        hit = memb[k] > 0.0
        if not hit.any():
            continue
        rr, k, s = rr[hit], k[hit], ids[k[hit]].astype(np.int64)
        present[rr] |= np.left_shift(np.uint32(1), s.astype(np.uint32))
        np.add.at(assigned, (s, rr), alpha_w[k])
        parts["ray"].append(rr)
        parts["lut"].append(k.astype(np.uint16))
        if shade:
            acc = np.zeros((len(rr), 3))
            for w, (dx, dy, dz) in zip(weights, _CORNERS, strict=True):
                m = nrm[z[hit] + dz, y[hit] + dy, x[hit] + dx].astype(np.float64)
                sign = np.where(m @ view > 0.0, -1.0, 1.0)
                acc += (w[hit] * sign)[:, None] * m
            parts["nrm"].append(np.rint(acc).astype(np.int8))
        if has_curv:
            q = np.floor(p[hit] + 0.5).astype(np.int64)
            parts["curv"].append(curv[q[:, 2], q[:, 1], q[:, 0]].astype(np.float32))
    if parts["ray"]:
        ray = np.concatenate(parts["ray"])
        srt = np.argsort(ray, kind="stable")
        lut = np.concatenate(parts["lut"])[srt]
        nrm_e = np.concatenate(parts["nrm"])[srt] if shade else np.zeros((0, 3), np.int8)
        curv_e = np.concatenate(parts["curv"])[srt] if has_curv else np.zeros(0, np.float32)
        counts = np.bincount(ray, minlength=nrays)
    else:
        lut = np.zeros(0, np.uint16)
        nrm_e = np.zeros((0, 3), np.int8)
        curv_e = np.zeros(0, np.float32)
        counts = np.zeros(nrays, np.int64)
    off = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return {
        "off": off,
        "lut": lut,
        "nrm": nrm_e,
        "curv": curv_e,
        "present": present,
        "assigned": assigned,
    }


def composite(
    start,
    counts,
    c_lut,
    c_nrm,
    c_curv,
    ids,
    alpha_r,
    col,
    light,
    stab,
    shade,
    has_curv,
    ert,
    k_count,
):
    """Front-to-back compositing of cached entries; returns rgba (R, 4), vis (K, R), curv (R,)."""
    nrays = len(start)
    tr = np.ones(nrays)
    rgb = np.zeros((nrays, 3))
    vis = np.zeros((k_count, nrays))
    num = np.zeros(nrays)
    den = np.zeros(nrays)
    alive = np.ones(nrays, bool)
    order = np.argsort(-counts, kind="stable")
    neg = -counts[order]
    for e in range(int(-neg[0]) if nrays else 0):
        rr = order[: np.searchsorted(neg, -e, side="left")]
        rr = rr[alive[rr]]
        if rr.size == 0:
            break
        ent = start[rr] + e
        k = c_lut[ent].astype(np.int64)
        al = alpha_r[k].astype(np.float64)
        s = ids[k].astype(np.int64)
        dfac = np.ones(len(rr))
        spec = np.zeros(len(rr))
        if shade:
            dfac, spec = _shade(c_nrm[ent], s, light, stab)
        w = al * tr[rr]
        np.add.at(vis, (s, rr), w)
        rgb[rr] += w[:, None] * (col[s] * dfac[:, None] + spec[:, None])
        if has_curv:
            hc = c_curv[ent].astype(np.float64)
            pos = hc > 0.0
            num[rr[pos]] += w[pos] * hc[pos]
            den[rr[pos]] += w[pos]
        tr[rr] *= 1.0 - al
        alive[rr] = tr[rr] >= ert
    rgba = np.empty((nrays, 4))
    rgba[:, :3] = np.minimum(rgb, 1.0)
    rgba[:, 3] = 1.0 - tr
    with np.errstate(invalid="ignore", divide="ignore"):
        cimg = np.where(den > 0.0, num / den, 0.0)
    return rgba, vis, cimg
