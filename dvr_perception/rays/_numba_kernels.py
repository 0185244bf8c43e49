"""numba kernels of the ray-analysis engine (see :mod:`dvr_perception.rays.engine`).

Kernels, parallel over interleaved image rows:

* :func:`walk` marches every ray through the table-index volume at VTK's sample positions,
  skipping empty 8^3 blocks.  It always accumulates ``present`` and ``assigned`` over the whole
  ray.  With ``build`` it writes one cache entry per sample with membership > 0 (table index,
  quantised interpolated normal, float32 curvature) and composites nothing; without
  ``build`` it also composites front to back until early ray termination (colour,
  ``visible``, curvature).
* :func:`composite` re-composites from cache entries (no volume access).
* :func:`segments` sets up every pixel's ray; :func:`compact` packs the cache entries.

Both use :func:`_shade` and the same compositing update, so an analysis composited from the
cache equals one composited during the walk.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["compact", "composite", "segments", "walk"]

# VTK's fixed-point trilinear weights sum to 32765/32768 and the index is rounded up.
_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0


@njit(parallel=True, cache=True)
def segments(cam, a, b, t_first, nsteps):
    """Per-pixel rays and sample ranges; the numba twin of ``_grid.ray_segments``.

    ``cam`` is :func:`dvr_perception.rays._grid.camera_pack` output.
    """
    width = int(cam[14])
    height = int(cam[15])
    par = cam[13] != 0.0
    half = cam[12]
    aspect = cam[14] / cam[15]
    step = cam[27]
    lo = cam[28]
    for row in prange(height):
        ys = 1.0 - 2.0 * (row + 0.5) / height
        for col in range(width):
            r = row * width + col
            xs = 2.0 * (col + 0.5) / width - 1.0
            u = xs * (half * aspect)
            v = ys * half
            if par:
                o0 = cam[0] + u * cam[6] + v * cam[9]
                o1 = cam[1] + u * cam[7] + v * cam[10]
                o2 = cam[2] + u * cam[8] + v * cam[11]
                d0, d1, d2 = cam[3], cam[4], cam[5]
                cos = 1.0
            else:
                o0, o1, o2 = cam[0], cam[1], cam[2]
                d0 = cam[3] + u * cam[6] + v * cam[9]
                d1 = cam[4] + u * cam[7] + v * cam[10]
                d2 = cam[5] + u * cam[8] + v * cam[11]
                nrm = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                d0 /= nrm
                d1 /= nrm
                d2 /= nrm
                cos = max(d0 * cam[3] + d1 * cam[4] + d2 * cam[5], 1e-12)
            t_near = cam[25] / cos
            t_in = t_near
            t_out = cam[26] / cos
            hit = True
            for i in range(3):
                oi = o0 if i == 0 else (o1 if i == 1 else o2)
                di = d0 if i == 0 else (d1 if i == 1 else d2)
                ai = (oi - cam[16 + i]) / cam[19 + i]
                bi = di / cam[19 + i]
                a[r, i] = ai
                b[r, i] = bi
                if bi != 0.0:
                    t1 = (lo - ai) / bi
                    t2 = (cam[22 + i] - ai) / bi
                    t_in = max(t_in, min(t1, t2))
                    t_out = min(t_out, max(t1, t2))
                elif ai < lo or ai > cam[22 + i]:
                    hit = False
            nsteps[r] = 0
            t_first[r] = 0.0
            if hit and t_out > t_in:
                length = t_out - t_in
                t_in += 0.001 * length
                t_out -= 0.001 * length
                k0 = np.floor((t_in - t_near) / step) + 1.0
                k1 = np.floor((t_out - t_near) / step)
                if k1 >= k0:
                    nsteps[r] = int(k1 - k0 + 1.0)
                    t_first[r] = t_near + k0 * step


@njit(cache=True, fastmath=True)
def _shade(q0, q1, q2, s, lx, ly, lz, hx, hy, hz, ka, kd, stab):
    """Diffuse factor and specular term for a quantised normal (two-sided flip already done).

    ``stab[s]`` tabulates ``ks I x ** p`` at ``x = i / (len - 1)``; linear interpolation.
    """
    n0 = q0 / 127.0
    n1 = q1 / 127.0
    n2 = q2 / 127.0
    ndl = n0 * lx + n1 * ly + n2 * lz
    dfac = ka[s]
    spec = 0.0
    if ndl > 0.0:
        dfac += kd[s] * ndl
        ndh = n0 * hx + n1 * hy + n2 * hz
        if ndh > 0.001:
            u = min(ndh, 1.0) * (stab.shape[1] - 1)
            i = min(int(u), stab.shape[1] - 2)
            spec = stab[s, i] + (u - i) * (stab[s, i + 1] - stab[s, i])
    return dfac, spec


@njit(cache=True, fastmath=True)
def _normal(nrm, x, y, z, fx, fy, fz, vx, vy, vz):
    """Trilinear mix of the 8 corner normals, each flipped to face the viewer; int8-quantised."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for c in range(8):
        dx = c & 1
        dy = (c >> 1) & 1
        dz = c >> 2
        w = (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy) * (fz if dz else 1.0 - fz)
        m0 = float(nrm[z + dz, y + dy, x + dx, 0])
        m1 = float(nrm[z + dz, y + dy, x + dx, 1])
        m2 = float(nrm[z + dz, y + dy, x + dx, 2])
        if m0 * vx + m1 * vy + m2 * vz > 0.0:
            w = -w
        s0 += w * m0
        s1 += w * m1
        s2 += w * m2
    return np.int8(np.rint(s0)), np.int8(np.rint(s1)), np.int8(np.rint(s2))


@njit(cache=True, fastmath=True, inline="always")
def _walk_ray(
    r, idx, nrm, curv, flags, a, b, t_first, n, step, ids, memb, alpha_r, alpha_w, col, light, stab,
    shade, has_curv, build, base, ert, rgba, vis, asg, present, cimg, c_lut, c_nrm, c_curv,
):  # fmt: skip
    nz, ny, nx = idx.shape
    ka, kd = light[0], light[1]
    lx, ly, lz = light[4, 0], light[4, 1], light[4, 2]
    hx, hy, hz = light[5, 0], light[5, 1], light[5, 2]
    vx, vy, vz = light[6, 0], light[6, 1], light[6, 2]
    ax, ay, az = a[r, 0], a[r, 1], a[r, 2]
    bx, by, bz = b[r, 0], b[r, 1], b[r, 2]
    bits = np.uint32(0)
    cnt = 0
    walked = 0
    alive = not build
    tr = 1.0
    cr = 0.0
    cg = 0.0
    cb = 0.0
    num = 0.0
    den = 0.0
    j = 0
    while j < n:
        t = t_first + j * step
        px = ax + t * bx
        py = ay + t * by
        pz = az + t * bz
        x = min(max(int(px), 0), nx - 2)
        y = min(max(int(py), 0), ny - 2)
        z = min(max(int(pz), 0), nz - 2)
        if flags[z >> 3, y >> 3, x >> 3] == 0:
            # jump to the first sample past this block's exit
            te = 1e300
            if bx > 0.0:
                te = min(te, (((x >> 3) + 1) * 8 - ax) / bx)
            elif bx < 0.0:
                te = min(te, ((x >> 3) * 8 - ax) / bx)
            if by > 0.0:
                te = min(te, (((y >> 3) + 1) * 8 - ay) / by)
            elif by < 0.0:
                te = min(te, ((y >> 3) * 8 - ay) / by)
            if bz > 0.0:
                te = min(te, (((z >> 3) + 1) * 8 - az) / bz)
            elif bz < 0.0:
                te = min(te, ((z >> 3) * 8 - az) / bz)
            jn = int(np.ceil((te - t_first) / step))
            j = jn if jn > j else j + 1
            continue
        walked += 1
        fx = min(max(px - x, 0.0), 1.0)
        fy = min(max(py - y, 0.0), 1.0)
        fz = min(max(pz - z, 0.0), 1.0)
        gx = 1.0 - fx
        gy = 1.0 - fy
        gz = 1.0 - fz
        f = (
            gz * (gy * (gx * idx[z, y, x] + fx * idx[z, y, x + 1])
                  + fy * (gx * idx[z, y + 1, x] + fx * idx[z, y + 1, x + 1]))
            + fz * (gy * (gx * idx[z + 1, y, x] + fx * idx[z + 1, y, x + 1])
                    + fy * (gx * idx[z + 1, y + 1, x] + fx * idx[z + 1, y + 1, x + 1]))
        )  # fmt: skip
        k = min(int(f * _W_SCALE + _W_BIAS), len(ids) - 1)
        j += 1
        if memb[k] <= 0.0:
            continue
        s = ids[k]
        bits |= np.uint32(1) << np.uint32(s)
        asg[s, r] += alpha_w[k]
        if not (build or alive):
            continue
        q0 = np.int8(0)
        q1 = np.int8(0)
        q2 = np.int8(0)
        if shade:
            q0, q1, q2 = _normal(nrm, x, y, z, fx, fy, fz, vx, vy, vz)
        hc = 0.0
        if has_curv:
            hc = curv[int(pz + 0.5), int(py + 0.5), int(px + 0.5)]
        if build:
            e = base + cnt
            c_lut[e] = k
            if shade:
                c_nrm[e, 0] = q0
                c_nrm[e, 1] = q1
                c_nrm[e, 2] = q2
            if has_curv:
                c_curv[e] = hc
            cnt += 1
            continue
        al = alpha_r[k]
        if al <= 0.0:
            continue
        dfac = 1.0
        spec = 0.0
        if shade:
            dfac, spec = _shade(q0, q1, q2, s, lx, ly, lz, hx, hy, hz, ka, kd, stab)
        w = al * tr
        vis[s, r] += w
        cr += w * (col[s, 0] * dfac + spec)
        cg += w * (col[s, 1] * dfac + spec)
        cb += w * (col[s, 2] * dfac + spec)
        if hc > 0.0:
            num += w * hc
            den += w
        tr *= 1.0 - al
        if tr < ert:
            alive = False
    present[r] = bits
    if not build:
        rgba[r, 0] = min(cr, 1.0)
        rgba[r, 1] = min(cg, 1.0)
        rgba[r, 2] = min(cb, 1.0)
        rgba[r, 3] = 1.0 - tr
        cimg[r] = num / den if den > 0.0 else 0.0
    return cnt, walked


@njit(parallel=True, cache=True, fastmath=True)
def walk(
    idx, nrm, curv, flags, a, b, t_first, nsteps, step, height, width, ids, memb, alpha_r,
    alpha_w, col, light, stab, shade, has_curv, build, cap_off, ert, rgba, vis, asg, present, cimg,
    c_lut, c_nrm, c_curv, count, walked,
):  # fmt: skip
    """March all rays; see the module docstring.  Outputs are flat per ray (row-major)."""
    nchunk = min(height, 64)
    for c in prange(nchunk):
        for row in range(c, height, nchunk):
            for col_ in range(width):
                r = row * width + col_
                if nsteps[r] == 0:
                    continue
                cnt, wk = _walk_ray(
                    r, idx, nrm, curv, flags, a, b, t_first[r], nsteps[r], step, ids, memb,
                    alpha_r, alpha_w, col, light, stab, shade, has_curv, build, cap_off[r], ert,
                    rgba, vis, asg, present, cimg, c_lut, c_nrm, c_curv,
                )  # fmt: skip
                count[r] = cnt
                walked[r] = wk


@njit(parallel=True, cache=True, fastmath=True)
def compact(cap_off, count, off, src_lut, src_nrm, src_curv, lut, nrm, curv, shade, has_curv):
    """Copy each ray's entries from its capacity slot to the packed arrays."""
    for r in prange(len(count)):
        s0 = cap_off[r]
        d0 = off[r]
        for i in range(count[r]):
            lut[d0 + i] = src_lut[s0 + i]
            if shade:
                nrm[d0 + i, 0] = src_nrm[s0 + i, 0]
                nrm[d0 + i, 1] = src_nrm[s0 + i, 1]
                nrm[d0 + i, 2] = src_nrm[s0 + i, 2]
            if has_curv:
                curv[d0 + i] = src_curv[s0 + i]


@njit(parallel=True, cache=True, fastmath=True)
def composite(
    start, count, c_lut, c_nrm, c_curv, height, width, ids, alpha_r, col, light, stab, shade,
    has_curv, ert, rgba, vis, cimg,
):  # fmt: skip
    """Front-to-back compositing of cached entries with early ray termination."""
    ka, kd = light[0], light[1]
    lx, ly, lz = light[4, 0], light[4, 1], light[4, 2]
    hx, hy, hz = light[5, 0], light[5, 1], light[5, 2]
    nchunk = min(height, 64)
    for c in prange(nchunk):
        for row in range(c, height, nchunk):
            for col_ in range(width):
                r = row * width + col_
                tr = 1.0
                cr = 0.0
                cg = 0.0
                cb = 0.0
                num = 0.0
                den = 0.0
                for e in range(start[r], start[r] + count[r]):
                    k = c_lut[e]
                    al = alpha_r[k]
                    if al <= 0.0:
                        continue
                    s = ids[k]
                    dfac = 1.0
                    spec = 0.0
                    if shade:
                        dfac, spec = _shade(
                            c_nrm[e, 0], c_nrm[e, 1], c_nrm[e, 2], s, lx, ly, lz, hx, hy, hz,
                            ka, kd, stab,
                        )  # fmt: skip
                    w = al * tr
                    vis[s, r] += w
                    cr += w * (col[s, 0] * dfac + spec)
                    cg += w * (col[s, 1] * dfac + spec)
                    cb += w * (col[s, 2] * dfac + spec)
                    if has_curv:
                        hc = float(c_curv[e])
                        if hc > 0.0:
                            num += w * hc
                            den += w
                    tr *= 1.0 - al
                    if tr < ert:
                        break
                rgba[r, 0] = min(cr, 1.0)
                rgba[r, 1] = min(cg, 1.0)
                rgba[r, 2] = min(cb, 1.0)
                rgba[r, 3] = 1.0 - tr
                cimg[r] = num / den if den > 0.0 else 0.0
