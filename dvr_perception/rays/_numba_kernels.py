"""numba kernels of the ray-analysis engine (see :mod:`dvr_perception.rays.engine`).

Kernels, parallel over chunks of interleaved image rows:

* :func:`walk` marches every ray through the table-index volume at VTK's sample positions,
  jumping whole boxes of empty 8^3 blocks at once (:func:`_grid.block_distance`,
  tested only when the ray enters another block).  It always accumulates ``present`` and
  ``assigned`` over the whole ray (table-index lookups only).  With ``build`` it packs one cache
  entry per sample with membership > 0 (table index and sample index; normal and curvature
  marked "not yet computed") into its chunk's region and composites the ray from those fresh
  entries right away (:func:`_composite_ray`); without ``build`` it composites during the walk.
* :func:`composite` re-composites from cache entries (no volume access except below).
* Normals and curvature of an entry are computed lazily (:func:`_fill`) the first time
  compositing reaches it with non-zero opacity and stored in the cache, so entries behind
  early ray termination cost nothing until a re-evaluation with lower opacities reaches them.
  Sample positions are recomputed bit-identically from the sample index (no fp contraction).
* :func:`segments` sets up every pixel's ray; :func:`compact` packs the chunks' entries.

Both compositing paths use :func:`_shade` and the same update, so an analysis composited from
the cache equals one composited during the walk.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["compact", "composite", "segments", "walk"]

# VTK's fixed-point trilinear weights sum to 32765/32768 and the index is rounded up.
_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0
#: fastmath without contraction or reassociation: sample positions are bit-identical wherever
#: they are recomputed (walk, lazy normal fill), so cached and fresh results agree exactly.
_FM = {"nnan", "ninf", "nsz", "arcp", "afn"}
#: Marks a cache entry whose normal (and curvature) has not been computed yet.
_UNSET = -128
_U1 = np.uint64(1)
_U2 = np.uint64(2)


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


@njit(cache=True, fastmath=_FM, inline="always")
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


@njit(cache=True, fastmath=_FM, inline="always")
def _normal(nrm, x, y, z, fx, fy, fz, vx, vy, vz):
    """Trilinear mix of the 8 corner normals, each flipped to face the viewer; int8-quantised."""
    f = nrm.reshape(nrm.size)
    sy = nrm.shape[2] * 3
    sz = nrm.shape[1] * sy
    o = z * sz + y * sy + x * 3
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for c in range(8):
        dx = c & 1
        dy = (c >> 1) & 1
        dz = c >> 2
        w = (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy) * (fz if dz else 1.0 - fz)
        p = np.uint64(o + dz * sz + dy * sy + dx * 3)
        m0 = float(f[p])
        m1 = float(f[p + _U1])
        m2 = float(f[p + _U2])
        w = -w if m0 * vx + m1 * vy + m2 * vz > 0.0 else w
        s0 += w * m0
        s1 += w * m1
        s2 += w * m2
    return np.int8(np.rint(s0)), np.int8(np.rint(s1)), np.int8(np.rint(s2))


@njit(cache=True, fastmath=_FM)
def _skip_to(j, t_first, step, dist, x, y, z, ax, ay, az, bx, by, bz):
    """First sample index past the empty box of blocks around the cell ``(x, y, z)``, or -1.

    ``dist`` is :func:`dvr_perception.rays._grid.block_distance`: every block within Chebyshev
    distance ``d - 1`` of a block with distance ``d`` is empty.
    """
    d = dist[z >> 3, y >> 3, x >> 3]
    if d == 0:
        return -1
    dm = int(d) - 1
    te = 1e300
    if bx > 0.0:
        te = min(te, (((x >> 3) + dm + 1) * 8 - ax) / bx)
    elif bx < 0.0:
        te = min(te, (((x >> 3) - dm) * 8 - ax) / bx)
    if by > 0.0:
        te = min(te, (((y >> 3) + dm + 1) * 8 - ay) / by)
    elif by < 0.0:
        te = min(te, (((y >> 3) - dm) * 8 - ay) / by)
    if bz > 0.0:
        te = min(te, (((z >> 3) + dm + 1) * 8 - az) / bz)
    elif bz < 0.0:
        te = min(te, (((z >> 3) - dm) * 8 - az) / bz)
    jn = int(np.ceil((te - t_first) / step))
    return jn if jn > j else j + 1


@njit(cache=True, fastmath=_FM, inline="always")
def _walk_ray(
    r, idx, nrm, curv, dist, a, b, t_first, n, step, ids, memb, alpha_r, alpha_w, col, light, stab,
    shade, has_curv, build, base, ert, rgba, vis, asg, present, cimg, out,
):  # fmt: skip
    """Walk one ray.

    ``build``: write cache entries (table index, sample index and the "not yet computed" marks
    of normal and curvature) and composite nothing; otherwise composite until early ray
    termination with normals computed on the fly.
    """
    c_lut, c_j, c_nrm, c_curv = out
    nz, ny, nx = idx.shape
    idxf = idx.reshape(idx.size)
    isy = np.uint64(nx)
    nxy = nx * ny
    isz = np.uint64(nxy)
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
    last_blk = -1
    while j < n:
        t = t_first + j * step
        px = ax + t * bx
        py = ay + t * by
        pz = az + t * bz
        x = min(max(int(px), 0), nx - 2)
        y = min(max(int(py), 0), ny - 2)
        z = min(max(int(pz), 0), nz - 2)
        blk = ((z >> 3) << 42) + ((y >> 3) << 21) + (x >> 3)
        if blk != last_blk:
            jn = _skip_to(j, t_first, step, dist, x, y, z, ax, ay, az, bx, by, bz)
            if jn >= 0:
                j = jn
                continue
            last_blk = blk
        walked += 1
        fx = min(max(px - x, 0.0), 1.0)
        fy = min(max(py - y, 0.0), 1.0)
        fz = min(max(pz - z, 0.0), 1.0)
        gx = 1.0 - fx
        gy = 1.0 - fy
        gz = 1.0 - fz
        o = np.uint64(z * nxy + y * nx + x)
        o1 = o + isy
        o2 = o + isz
        o3 = o2 + isy
        f = (
            gz * (gy * (gx * idxf[o] + fx * idxf[o + _U1])
                  + fy * (gx * idxf[o1] + fx * idxf[o1 + _U1]))
            + fz * (gy * (gx * idxf[o2] + fx * idxf[o2 + _U1])
                    + fy * (gx * idxf[o3] + fx * idxf[o3 + _U1]))
        )  # fmt: skip
        k = min(int(f * _W_SCALE + _W_BIAS), len(ids) - 1)
        if memb[k] <= 0.0:
            j += 1
            continue
        s = ids[k]
        bits |= np.uint32(1) << np.uint32(s)
        asg[s, r] += alpha_w[k]
        if build:
            e = base + cnt
            c_lut[e] = k
            c_j[e] = j
            if shade:
                c_nrm[e, 0] = _UNSET
            if has_curv:
                c_curv[e] = -1.0
            cnt += 1
            j += 1
            continue
        j += 1
        if not alive:
            continue
        al = alpha_r[k]
        if al <= 0.0:
            continue
        dfac = 1.0
        spec = 0.0
        if shade:
            q0, q1, q2 = _normal(nrm, x, y, z, fx, fy, fz, vx, vy, vz)
            dfac, spec = _shade(q0, q1, q2, s, lx, ly, lz, hx, hy, hz, ka, kd, stab)
        hc = 0.0
        if has_curv:
            hc = curv[int(pz + 0.5), int(py + 0.5), int(px + 0.5)]
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


@njit(cache=True, fastmath=_FM, inline="always")
def _fill(e, j, ax, ay, az, bx, by, bz, t_first, step, nrm, curv, vx, vy, vz, shade, has_curv,
          c_nrm, c_curv):  # fmt: skip
    """Compute entry ``e``'s normal and curvature from its sample index, as the walk would."""
    nz, ny, nx = nrm.shape[0], nrm.shape[1], nrm.shape[2]
    t = t_first + j * step
    px = ax + t * bx
    py = ay + t * by
    pz = az + t * bz
    if shade:
        x = min(max(int(px), 0), nx - 2)
        y = min(max(int(py), 0), ny - 2)
        z = min(max(int(pz), 0), nz - 2)
        fx = min(max(px - x, 0.0), 1.0)
        fy = min(max(py - y, 0.0), 1.0)
        fz = min(max(pz - z, 0.0), 1.0)
        q0, q1, q2 = _normal(nrm, x, y, z, fx, fy, fz, vx, vy, vz)
        c_nrm[e, 0] = q0
        c_nrm[e, 1] = q1
        c_nrm[e, 2] = q2
    if has_curv:
        c_curv[e] = curv[int(pz + 0.5), int(py + 0.5), int(px + 0.5)]


@njit(cache=True, fastmath=_FM, inline="always")
def _composite_ray(
    r, e0, cnt, c_lut, c_j, c_nrm, c_curv, a, b, t_first, step, nrm, curv, ids, alpha_r, col,
    light, stab, shade, has_curv, ert, rgba, vis, cimg,
):  # fmt: skip
    """Front-to-back compositing of ray ``r``'s entries with early ray termination.

    Normals and curvature of entries reached for the first time are computed and stored.
    """
    ka, kd = light[0], light[1]
    lx, ly, lz = light[4, 0], light[4, 1], light[4, 2]
    hx, hy, hz = light[5, 0], light[5, 1], light[5, 2]
    vx, vy, vz = light[6, 0], light[6, 1], light[6, 2]
    tr = 1.0
    cr = 0.0
    cg = 0.0
    cb = 0.0
    num = 0.0
    den = 0.0
    for e in range(e0, e0 + cnt):
        k = c_lut[e]
        al = alpha_r[k]
        if al <= 0.0:
            continue
        s = ids[k]
        if (shade and c_nrm[e, 0] == _UNSET) or (has_curv and c_curv[e] < 0.0):
            _fill(e, c_j[e], a[r, 0], a[r, 1], a[r, 2], b[r, 0], b[r, 1], b[r, 2], t_first[r],
                  step, nrm, curv, vx, vy, vz, shade, has_curv, c_nrm, c_curv)  # fmt: skip
        dfac = 1.0
        spec = 0.0
        if shade:
            dfac, spec = _shade(
                c_nrm[e, 0], c_nrm[e, 1], c_nrm[e, 2], s, lx, ly, lz, hx, hy, hz, ka, kd, stab
            )
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


@njit(parallel=True, cache=True, fastmath=_FM)
def walk(
    idx, nrm, curv, dist, a, b, t_first, nsteps, step, height, width, nchunk, ids, memb, alpha_r,
    alpha_w, col, light, stab, shade, has_curv, build, chunk_base, ert, rgba, vis, asg, present,
    cimg, c_lut, c_j, c_nrm, c_curv, start, count, chunk_end, walked,
):  # fmt: skip
    """March all rays; see the module docstring.  Outputs are flat per ray (row-major).

    Chunk ``c`` (rows ``c, c + nchunk, ...``) packs its rays' entries from ``chunk_base[c]``
    on and records its end in ``chunk_end[c]``; with ``build`` each ray is composited from its
    fresh entries right after its walk.
    """
    for c in prange(nchunk):
        e = chunk_base[c]
        for row in range(c, height, nchunk):
            for col_ in range(width):
                r = row * width + col_
                start[r] = e
                count[r] = 0
                if nsteps[r] == 0:
                    continue
                cnt, wk = _walk_ray(
                    r, idx, nrm, curv, dist, a, b, t_first[r], nsteps[r], step, ids, memb,
                    alpha_r, alpha_w, col, light, stab, shade, has_curv, build, e, ert,
                    rgba, vis, asg, present, cimg, (c_lut, c_j, c_nrm, c_curv),
                )  # fmt: skip
                if build:
                    _composite_ray(
                        r, e, cnt, c_lut, c_j, c_nrm, c_curv, a, b, t_first, step, nrm, curv,
                        ids, alpha_r, col, light, stab, shade, has_curv, ert, rgba, vis, cimg,
                    )  # fmt: skip
                count[r] = cnt
                walked[r] = wk
                e += cnt
        chunk_end[c] = e


@njit(parallel=True, cache=True)
def compact(height, width, nchunk, chunk_base, chunk_end, dest, start, src_lut, src_j, src_nrm,
            src_curv, lut, j_, nrm, curv, shade, has_curv):  # fmt: skip
    """Move each chunk's packed entries to ``dest[c]`` and shift its rays' ``start``."""
    for c in prange(nchunk):
        s0 = chunk_base[c]
        d0 = dest[c]
        for i in range(chunk_end[c] - s0):
            lut[d0 + i] = src_lut[s0 + i]
            j_[d0 + i] = src_j[s0 + i]
            if shade:
                nrm[d0 + i, 0] = src_nrm[s0 + i, 0]
                nrm[d0 + i, 1] = src_nrm[s0 + i, 1]
                nrm[d0 + i, 2] = src_nrm[s0 + i, 2]
            if has_curv:
                curv[d0 + i] = src_curv[s0 + i]
        for row in range(c, height, nchunk):
            for col_ in range(width):
                start[row * width + col_] += d0 - s0


@njit(parallel=True, cache=True, fastmath=_FM)
def composite(
    start, count, c_lut, c_j, c_nrm, c_curv, a, b, t_first, step, nrm, curv, height, width,
    nchunk, ids, alpha_r, col, light, stab, shade, has_curv, ert, rgba, vis, cimg,
):  # fmt: skip
    """Front-to-back compositing of cached entries with early ray termination.

    No volume access except for normals and curvature of entries never reached before.
    """
    for c in prange(nchunk):
        for row in range(c, height, nchunk):
            for col_ in range(width):
                r = row * width + col_
                _composite_ray(
                    r, start[r], count[r], c_lut, c_j, c_nrm, c_curv, a, b, t_first, step, nrm,
                    curv, ids, alpha_r, col, light, stab, shade, has_curv, ert, rgba, vis, cimg,
                )  # fmt: skip


@njit(parallel=True, cache=True)
def check_curvature(c):
    """0 if every value of ``c`` (flat) is finite and >= 0, 1 if finite with negatives, else 2."""
    n = c.size
    nchunk = 64
    bad = np.zeros(nchunk, np.uint8)
    for ch in prange(nchunk):
        b = 0
        for i in range(ch * n // nchunk, (ch + 1) * n // nchunk):
            v = c[i]
            if not np.isfinite(v):
                b = 2
            elif v < 0.0 and b == 0:
                b = 1
        bad[ch] = b
    return bad.max()


@njit(parallel=True, cache=True)
def finish(rgba, vis, cimg, bg, rgba32, image, acc, vis32, cimg32):
    """float32 outputs and the image over the background (as ``engine._finish`` in numpy)."""
    k = vis.shape[0]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for r in prange(rgba.shape[0]):
        a = np.float32(rgba[r, 3])
        for c in range(3):
            v = np.float32(rgba[r, c])
            rgba32[r, c] = v
            im = v + (one - a) * bg[c]
            image[r, c] = min(max(im, zero), one)
        rgba32[r, 3] = a
        acc[r] = a
        cimg32[r] = np.float32(cimg[r])
        for s in range(k):
            vis32[s, r] = np.float32(vis[s, r])
