"""Pure-numpy back end of the ray-analysis engine (used when numba is unavailable).

Same sample positions, table lookups, shading and compositing as
:mod:`dvr_perception.rays._numba_kernels`, vectorised over all rays that are still inside the
volume at each step.  It does no empty-space skipping (skipping never changes results) and
always builds the cache entries, then composites them with :func:`composite`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["composite", "walk"]

_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0
_IQS = 1.0 / 65534.0
_CORNERS = [((c & 1), (c >> 1) & 1, c >> 2) for c in range(8)]


def shade_entries(vol, seg, step, start, count, steps, s, tab, shade) -> np.ndarray:
    """VTK shading of every entry (see the numba ``_shade_at``): uint16 (E, 2), or (0, 2).

    Positions are recomputed from the sample index ``steps`` exactly as the numba kernels do.
    """
    if not shade:
        return np.zeros((0, 2), np.uint16)
    a, b, t_first = seg["a"], seg["b"], seg["t"]
    nz, ny, nx = vol.shape
    flat = vol.reshape(-1)
    ray = np.repeat(np.arange(len(start)), count)
    out = np.empty((len(ray), 2), np.uint16)
    for e0 in range(0, len(ray), 1 << 20):
        sl = slice(e0, e0 + (1 << 20))
        rr, ss = ray[sl], s[sl].astype(np.int64)
        t = t_first[rr] + steps[sl] * step
        p = a[rr] + t[:, None] * b[rr]
        cell = np.minimum(np.maximum(p.astype(np.int64), 0), np.array([nx, ny, nz]) - 2)
        f = np.clip(p - cell, 0.0, 1.0)
        g = 1.0 - f
        o = cell[:, 2] * (nx * ny) + cell[:, 1] * nx + cell[:, 0]
        dl = np.zeros(len(rr))
        sp = np.zeros(len(rr))
        for dx, dy, dz in _CORNERS:
            w = (f[:, 2] if dz else g[:, 2]) * (f[:, 1] if dy else g[:, 1])
            w = w * (f[:, 0] if dx else g[:, 0])
            code = (flat[o + dz * nx * ny + dy * nx + dx] >> 16).astype(np.int64)
            dl = dl + w * tab[ss, code, 0].astype(np.float64)
            sp = sp + w * tab[ss, code, 1].astype(np.float64)  # table units (x 65534)
        out[sl, 0] = np.minimum(np.floor(dl + 0.5), 65534)
        out[sl, 1] = np.minimum(np.floor(sp + 0.5), 65534)
    return out


def walk(idx, lab, lab_base, curv, seg, step, ids, memb, alpha_w, has_curv, k_count, ert):
    """March all rays; return cache entries in ray order plus ``present`` and ``assigned``.

    ``lab`` (uint8 label map) overrides the interpolated table entry with entry
    ``lab_base + lab - 1`` where a sample's nearest voxel is labelled (``lab_base`` -1: none).

    Returns a dict with ``off`` (R+1 int64), ``lut`` (uint16), ``steps`` (int32 sample index),
    ``curv`` (float32), ``present`` (uint32 R), ``assigned`` (float64 (K, R)) and
    ``importance_accumulated`` (float64 R: the accumulated opacity at the importance opacities
    ``alpha_w``, with early ray termination below transmittance ``ert``).
    """
    a, b, t_first, n = seg["a"], seg["b"], seg["t"], seg["n"]
    nrays = len(n)
    nz, ny, nx = idx.shape
    present = np.zeros(nrays, np.uint32)
    assigned = np.zeros((k_count, nrays))
    ti = np.ones(nrays)
    order = np.argsort(-n.astype(np.int64), kind="stable")
    neg = -n[order].astype(np.int64)
    parts: dict[str, list] = {"ray": [], "lut": [], "steps": [], "curv": []}
    for j in range(int(-neg[0]) if nrays else 0):
        rr = order[: np.searchsorted(neg, -j, side="left")]
        t = t_first[rr] + j * step
        p = a[rr] + t[:, None] * b[rr]
        cell = np.minimum(np.maximum(p.astype(np.int64), 0), np.array([nx, ny, nz]) - 2)
        frac = np.clip(p - cell, 0.0, 1.0)
        x, y, z = cell[:, 0], cell[:, 1], cell[:, 2]
        f = np.zeros(len(rr))
        for dx, dy, dz in _CORNERS:
            w = (
                (frac[:, 0] if dx else 1.0 - frac[:, 0])
                * (frac[:, 1] if dy else 1.0 - frac[:, 1])
                * (frac[:, 2] if dz else 1.0 - frac[:, 2])
            )
            f += w * idx[z + dz, y + dy, x + dx]
        k = np.minimum(
            (f * _W_SCALE + _W_BIAS).astype(np.int64), (lab_base if lab_base >= 0 else len(ids)) - 1
        )
        if lab_base >= 0:
            q = np.floor(p + 0.5).astype(np.int64)
            lv = lab[q[:, 2], q[:, 1], q[:, 0]].astype(np.int64)
            k = np.where(lv > 0, lab_base + lv - 1, k)
        hit = memb[k] > 0.0
        if not hit.any():
            continue
        rr, k, s = rr[hit], k[hit], ids[k[hit]].astype(np.int64)
        present[rr] |= np.left_shift(np.uint32(1), s.astype(np.uint32))
        np.add.at(assigned, (s, rr), alpha_w[k])
        live = ti[rr] >= ert  # rays are distinct within a step
        ti[rr[live]] *= 1.0 - alpha_w[k[live]]
        parts["ray"].append(rr)
        parts["lut"].append(k.astype(np.uint16))
        parts["steps"].append(np.full(len(rr), j, np.int32))
        if has_curv:
            q = np.floor(p[hit] + 0.5).astype(np.int64)
            parts["curv"].append(curv[q[:, 2], q[:, 1], q[:, 0]].astype(np.float32))
    if parts["ray"]:
        ray = np.concatenate(parts["ray"])
        srt = np.argsort(ray, kind="stable")
        lut = np.concatenate(parts["lut"])[srt]
        steps = np.concatenate(parts["steps"])[srt]
        curv_e = np.concatenate(parts["curv"])[srt] if has_curv else np.zeros(0, np.float32)
        counts = np.bincount(ray, minlength=nrays)
    else:
        lut = np.zeros(0, np.uint16)
        steps = np.zeros(0, np.int32)
        curv_e = np.zeros(0, np.float32)
        counts = np.zeros(nrays, np.int64)
    off = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return {
        "off": off,
        "lut": lut,
        "steps": steps,
        "curv": curv_e,
        "present": present,
        "assigned": assigned,
        "importance_accumulated": 1.0 - ti,
    }


def composite(
    start,
    counts,
    c_lut,
    c_sh,
    c_curv,
    ids,
    alpha_r,
    col,
    light,
    tab,
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
            sh = c_sh[ent].astype(np.float64)
            dfac = light[0, s] + light[1, s] * (sh[:, 0] * _IQS)
            spec = light[2, s] * (sh[:, 1] * _IQS)
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
