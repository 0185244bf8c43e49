"""numba kernels of the bricked analysis (:mod:`dvr_perception.rays.bricks`).

A brick owns a box of the whole volume's cells; a ray's samples in it are one run ``[j0, j1)``
of its sample indices (the ray is straight and the box convex).  :func:`brick_ranges` finds
that run exactly: per axis, the first sample whose cell (as :func:`_numba_kernels._sample_at`
computes it, the whole volume's cell) reaches the box's bounds, by an analytic estimate made
exact by stepping.  Neighbouring bricks evaluate the same test at their shared plane, so every
sample of a ray belongs to exactly one brick.  :func:`walk_brick` walks those samples with
:func:`_numba_kernels._walk_ray`, continuing the per-ray state handed on from the bricks in
front; :func:`fill_range` computes the shading and curvature of cache entries in a brick's
runs (the bricked cache has no whole volume to fill them from later); :func:`place` copies a
brick's cache entries behind the entries of the bricks in front of it (:func:`place_all`: every
brick's at once, when they share one buffer); :func:`composite_part`
re-composites a brick's cache entries, continuing the rays' state from the bricks in front
(the re-evaluation over MPI ranks, :class:`~dvr_perception.distributed.RankSession`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from dvr_perception.rays._numba_grid import _ZERO_CODE, _code
from dvr_perception.rays._numba_kernels import (
    _BLOCK,
    _CELL_EMPTY,
    _CELL_MIXED,
    _FM,
    _IQS,
    _U1,
    _UNSET,
    _block_skip,
    _fill,
    _jump_scale,
    _sample_at,
    _shade_at,
    _table_index,
    _walk_ray,
)

__all__ = [
    "any_alive",
    "brick_ranges",
    "composite_part",
    "crossing",
    "fill_from_data",
    "fill_range",
    "place",
    "place_all",
    "reach",
    "reached_blocks",
    "records_reached",
    "walk_brick",
]


@njit(cache=True, fastmath=_FM, inline="always")
def _cell(j, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz, axis):
    _, _, _, x, y, z = _sample_at(j, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz)
    return x if axis == 0 else (y if axis == 1 else z)


@njit(cache=True, fastmath=_FM, inline="always")
def _first(c, axis, rising, t_first, step, n, ax, ay, az, bx, by, bz, gnx, gny, gnz):
    """First sample index in ``[0, n]`` whose cell along ``axis`` has passed plane ``c``.

    ``rising``: the cell index grows along the ray (test ``cell >= c``), else it falls (test
    ``cell < c``).  The test is monotone along the ray, so stepping from the estimate is exact.
    """
    ai = ax if axis == 0 else (ay if axis == 1 else az)
    bi = bx if axis == 0 else (by if axis == 1 else bz)
    est = ((c - ai) / bi - t_first) / step
    j = 0
    if est >= n:
        j = n
    elif est > 0.0:
        j = math.ceil(est)
    while j > 0:
        cj = _cell(j - 1, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz, axis)
        if (cj >= c) if rising else (cj < c):
            j -= 1
        else:
            break
    while j < n:
        cj = _cell(j, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz, axis)
        if (cj >= c) if rising else (cj < c):
            break
        j += 1
    return j


@njit(parallel=True, cache=True, fastmath=_FM)
def brick_ranges(a, b, t_first, nsteps, step, lo, hi, gdims, j0, j1):
    """Per ray, the run ``[j0, j1)`` of its samples whose cell is in ``[lo, hi)`` (x, y, z)."""
    gnx, gny, gnz = gdims[0], gdims[1], gdims[2]
    for r in prange(len(nsteps)):
        n = nsteps[r]
        s0 = 0
        s1 = n
        if n > 0:
            ax, ay, az = a[r, 0], a[r, 1], a[r, 2]
            bx, by, bz = b[r, 0], b[r, 1], b[r, 2]
            tf = t_first[r]
            for axis in range(3):
                bi = bx if axis == 0 else (by if axis == 1 else bz)
                if lo[axis] <= 0 and hi[axis] >= gdims[axis] - 1:
                    continue  # the brick spans the axis: no bound
                if bi == 0.0:
                    c = _cell(0, tf, step, ax, ay, az, bx, by, bz, gnx, gny, gnz, axis)
                    if c < lo[axis] or c >= hi[axis]:
                        s1 = 0
                    continue
                up = bi > 0.0
                c_in = lo[axis] if up else hi[axis]
                c_out = hi[axis] if up else lo[axis]
                f_in = _first(c_in, axis, up, tf, step, n, ax, ay, az, bx, by, bz, gnx, gny, gnz)
                f_out = _first(c_out, axis, up, tf, step, n, ax, ay, az, bx, by, bz, gnx, gny,
                               gnz)  # fmt: skip
                s0 = max(s0, f_in)
                s1 = min(s1, f_out)
        j0[r] = s0
        j1[r] = max(s1, s0)


@njit(parallel=True, cache=True, fastmath=_FM)
def walk_brick(
    vol, tix, cells, blocks, occ, rep, lab, lab_base, kmap, tids, t_alpha, t_bit, smask, sdist, cap,
    curv, a,
    b, t_first, j0, j1, step, order, chunk_ptr, nchunk, ids, memb, alpha_r, alpha_w, col, light,
    tab, shade, has_curv, build, tail, chunk_base, ert, geo, st, bits, vis, asg, c_lut, c_j, c_sh,
    c_curv, start, count, walked,
):  # fmt: skip
    """Walk every ray's run ``[j0, j1)`` in this brick, continuing the state ``st``/``bits``.

    ``st`` (R, 7) float64 holds ``cr, cg, cb, tr, ti, num, den`` per ray, ``bits`` the present
    bits; ``vis`` (K, R) and ``asg`` (K + 1, R) are added to.  Otherwise as
    :func:`_numba_kernels.walk` (chunk ``c`` packs its cache entries from ``chunk_base[c]``).
    """
    for c in prange(nchunk):
        maps = (
            tix,
            cells,
            blocks,
            occ,
            rep,
            lab,
            lab_base,
            (kmap, tids, t_alpha, t_bit, smask, sdist, cap),
        )
        g = (geo[0], geo[1], geo[2], geo[3], geo[4], geo[5])
        e = chunk_base[c]
        for i in range(chunk_ptr[c], chunk_ptr[c + 1]):
            r = order[i]
            start[r] = e
            count[r] = 0
            walked[r] = 0
            if j1[r] <= j0[r]:
                continue
            cnt, wk = _walk_ray(
                r, vol, maps, curv, a, b, t_first[r], (j0[r], j1[r]), step, ids, memb,
                alpha_r, alpha_w, col, light, tab, shade, has_curv, build, tail, e, ert,
                vis, asg, st, bits, g, (c_lut, c_j, c_sh, c_curv),
            )  # fmt: skip
            count[r] = cnt
            walked[r] = wk
            e += cnt


@njit(parallel=True, cache=True, fastmath=_FM)
def fill_range(start, count, c_lut, c_j, c_sh, c_curv, a, b, t_first, step, j0, j1, vol, curv,
               geo, ids, tab, shade, has_curv, shift):  # fmt: skip
    """Compute shading and curvature of the unset entries whose sample is in ``[j0, j1)``.

    ``vol``/``curv`` are the brick's (global index of their first voxel in ``geo[3:]``;
    ``vol``: voxel records, ``shift`` 16, or bare normal codes, 0); a ray's entries are in
    sample order, so its run starts at a binary-searched entry.
    """
    g = (geo[0], geo[1], geo[2], geo[3], geo[4], geo[5])
    for r in prange(len(start)):
        if j1[r] <= j0[r] or count[r] == 0:
            continue
        lo = start[r]
        hi = start[r] + count[r]
        while lo < hi:  # first entry with sample index >= j0
            mid = (lo + hi) // 2
            if c_j[mid] < j0[r]:
                lo = mid + 1
            else:
                hi = mid
        end = start[r] + count[r]
        for e in range(lo, end):
            j = c_j[e]
            if j >= j1[r]:
                break
            unset = (shade and c_sh[e, 0] == _UNSET) or (has_curv and c_curv[e] < 0.0)
            if unset:
                _fill(e, j, a[r, 0], a[r, 1], a[r, 2], b[r, 0], b[r, 1], b[r, 2], t_first[r],
                      step, vol, curv, tab, ids[c_lut[e]], shade, has_curv, c_sh, c_curv, g,
                      shift)  # fmt: skip


#: :func:`_numba_grid._code` as a call of its own, compiled without fast-math as in the kernels
#: that make the voxel records (the fast-math kernel that calls it leaves its arithmetic alone).
_code_call = njit(cache=True)(_code.py_func)


@njit(parallel=True, cache=True, fastmath=_FM)
def fill_from_data(start, count, c_lut, c_j, c_sh, a, b, t_first, step, data, aspect, ids, tab):
    """Shade every entry whose shading is unset, its cell's 8 normal codes computed from ``data``.

    ``data``: the whole volume (``[z, y, x]``); the codes are :func:`_numba_grid._code`'s,
    the voxel records' (a brick's corner voxels have their neighbours in its piece, ghost
    layer included, or lie on the volume's border), so an entry's shading equals
    :func:`fill_range`'s from the brick's records, without deriving them: a change of light
    costs the cache's entries instead of every voxel of the bricks not kept.
    """
    nz, ny, nx = data.shape
    ax, ay, az = aspect[0], aspect[1], aspect[2]
    zero = np.uint64(0)
    two = np.uint64(2)
    four = np.uint64(4)
    for r in prange(len(start)):
        if count[r] == 0:
            continue
        loc = np.empty(8, np.uint32)  # the cell's codes, (z, y, x) corners as in _shade_at
        for e in range(start[r], start[r] + count[r]):
            if c_sh[e, 0] != _UNSET:
                continue
            px, py, pz, x, y, z = _sample_at(c_j[e], t_first[r], step, a[r, 0], a[r, 1], a[r, 2],
                                             b[r, 0], b[r, 1], b[r, 2], nx, ny, nz)  # fmt: skip
            fx = min(max(px - x, 0.0), 1.0)
            fy = min(max(py - y, 0.0), 1.0)
            fz = min(max(pz - z, 0.0), 1.0)
            q = 0
            for dz in range(2):
                for dy in range(2):
                    for dx in range(2):
                        loc[q] = np.uint32(
                            _code_call(data, z + dz, y + dy, x + dx, nz, ny, nx, ax, ay, az)
                        )
                        q += 1
            dl, sp = _shade_at(loc, zero, two, four, fx, fy, fz, tab, ids[c_lut[e]],
                               np.uint32(0))  # fmt: skip
            c_sh[e, 0] = dl
            c_sh[e, 1] = sp


@njit(parallel=True, cache=True)
def place(dest, fill, start, count, lut, j_, sh, curv, m_lut, m_j, m_sh, m_curv, shade, has_curv):
    """Append every ray's entries of one brick behind those already placed (``fill[r]``)."""
    for r in prange(len(dest)):
        d0 = dest[r] + fill[r]
        s0 = start[r]
        for q in range(count[r]):
            m_lut[d0 + q] = lut[s0 + q]
            m_j[d0 + q] = j_[s0 + q]
            if shade:
                m_sh[d0 + q, 0] = sh[s0 + q, 0]
                m_sh[d0 + q, 1] = sh[s0 + q, 1]
            if has_curv:
                m_curv[d0 + q] = curv[s0 + q]
        fill[r] += count[r]


@njit(parallel=True, cache=True)
def place_all(dest, starts, counts, lut, j_, sh, curv, m_lut, m_j, m_sh, m_curv, shade, has_curv):
    """Every brick's entries of every ray, one after another (:func:`place` for all bricks).

    ``starts``/``counts`` (B, R): per brick (in view order) each ray's first entry in the
    buffers ``lut``, ``j_``, ``sh``, ``curv`` that hold every brick's entries, and their
    number.  A ray's entries are written once, front to back, instead of one pass over the
    merged arrays per brick.
    """
    nb = starts.shape[0]
    for r in prange(len(dest)):
        d = dest[r]
        for q in range(nb):
            s0 = starts[q, r]
            n = counts[q, r]
            for i in range(n):
                m_lut[d + i] = lut[s0 + i]
                m_j[d + i] = j_[s0 + i]
                if shade:
                    m_sh[d + i, 0] = sh[s0 + i, 0]
                    m_sh[d + i, 1] = sh[s0 + i, 1]
                if has_curv:
                    m_curv[d + i] = curv[s0 + i]
            d += n


@njit(parallel=True, cache=True, fastmath=_FM)
def composite_part(start, count, c_lut, c_sh, c_curv, ids, alpha_r, col, light, shade, has_curv,
                   ert, st, vis):  # fmt: skip
    """Front-to-back compositing of one brick's cache entries, continuing every ray's state.

    ``st`` (R, 6) float64: premultiplied r, g, b, transmittance, curvature numerator and
    weight per ray; ``vis`` (K, R) float64 visible opacities; both updated in place.  The
    update is :func:`_numba_kernels._composite_ray`'s, operation for operation, and a ray
    whose transmittance is already below ``ert`` (terminated in a brick in front) is left as
    it is, so walking the bricks in view order gives the whole re-evaluation bit for bit.
    Every entry's shading and curvature must be set (:func:`fill_range`).
    """
    ka = light[0]
    kd = light[1]
    ks = light[2]
    for r in prange(len(start)):
        tr = st[r, 3]
        if count[r] == 0 or tr < ert:
            continue
        cr = st[r, 0]
        cg = st[r, 1]
        cb = st[r, 2]
        num = st[r, 4]
        den = st[r, 5]
        for e in range(start[r], start[r] + count[r]):
            k = c_lut[e]
            al = alpha_r[k]
            if al <= 0.0:
                continue
            s = ids[k]
            dfac = 1.0
            spec = 0.0
            if shade:
                dfac = ka[s] + kd[s] * (c_sh[e, 0] * _IQS)
                spec = ks[s] * (c_sh[e, 1] * _IQS)
            w = al * tr
            vis[s, r] += w
            cr += w * (col[s, 0] * dfac + spec)
            cg += w * (col[s, 1] * dfac + spec)
            cb += w * (col[s, 2] * dfac + spec)
            if has_curv:
                hc = c_curv[e]
                if hc > 0.0:
                    num += w * hc
                    den += w
            tr *= 1.0 - al
            if tr < ert:
                break
        st[r, 0] = cr
        st[r, 1] = cg
        st[r, 2] = cb
        st[r, 3] = tr
        st[r, 4] = num
        st[r, 5] = den


@njit(parallel=True, cache=True, fastmath=_FM)
def reach(start, count, c_lut, alpha, ert, out):
    """Per ray, how many of its entries compositing at ``alpha`` can reach, with a margin.

    Compositing (:func:`_numba_kernels._composite_ray`) stops after the entry that takes the
    transmittance below ``ert``; here the count runs on until it falls below ``ert / 2`` and
    one entry further, so rounding cannot make compositing reach past it.  Where the
    transmittance never falls that far: every entry.  A lazily shaded bricked cache shades
    these entries before it is composited (:func:`fill_range` on ``[start, start + out)``).
    """
    half = 0.5 * ert
    for r in prange(len(start)):
        tr = 1.0
        e0 = start[r]
        n = count[r]
        q = 0
        while q < n:
            al = alpha[c_lut[e0 + q]]
            q += 1
            if al > 0.0:
                tr *= 1.0 - al
                if tr < half:
                    break
        out[r] = min(q + 1, n)


@njit(parallel=True, cache=True, fastmath=_FM)
def reached_blocks(index, cells, blocks, rep, lab, lab_base, memb, alpha_r, a, b, t_first, j0,
                   j1, step, tr0, ert, geo, mask):  # fmt: skip
    """Mark the blocks of cells where a render's walk of this brick can shade a sample.

    A walk without a cache shades a sample only while its ray is short of early ray
    termination (:func:`_numba_kernels._walk_ray`): here every ray's run ``[j0, j1)`` is
    stepped as the walk steps it (the same sample positions, empty-space jumps and table
    entries; ``tr0`` its transmittance on entering the brick) with the rendering opacities
    ``alpha_r`` only, and the block (``_grid.BLOCK`` cells a side, the brick's block map's)
    of every non-empty cell met is marked in ``mask`` until the transmittance falls below
    ``0.99 ert`` (below the walk's stop: the same products, and a margin).
    ``index``: the brick's table index per voxel; ``geo`` as :func:`walk_brick`'s.
    """
    gnx, gny, gnz, ox, oy, oz = geo[0], geo[1], geo[2], geo[3], geo[4], geo[5]
    ny, nx = index.shape[1], index.shape[2]
    flat = index.reshape(index.size)
    clf = cells.reshape(cells.size)
    isy = np.uint64(nx)
    nxy = nx * ny
    isz = np.uint64(nxy)
    lab_end = (lab_base if lab_base >= 0 else len(memb)) - 1
    half = 0.99 * ert
    for r in prange(len(j0)):
        j = j0[r]
        n = j1[r]
        tr = tr0[r]
        if n <= j or tr < ert:
            continue
        ax, ay, az = a[r, 0], a[r, 1], a[r, 2]
        bx, by, bz = b[r, 0], b[r, 1], b[r, 2]
        tf = t_first[r]
        binv = _jump_scale(bx, by, bz, step) * _BLOCK
        while j < n:
            px, py, pz, x, y, z = _sample_at(j, tf, step, ax, ay, az, bx, by, bz, gnx, gny, gnz)
            skip = _block_skip(blocks, x - ox, y - oy, z - oz, binv)
            if skip:
                j += skip
                continue
            o = np.uint64((z - oz) * nxy + (y - oy) * nx + (x - ox))
            cl = clf[o]
            j += 1
            if cl == _CELL_EMPTY:
                continue
            mask[(z - oz) >> 2, (y - oy) >> 2, (x - ox) >> 2] = True
            lv = 0
            if cl != _CELL_MIXED:
                k = rep[cl - 1]
            elif lab_base >= 0:
                lv = lab[int(pz + 0.5) - oz, int(py + 0.5) - oy, int(px + 0.5) - ox]
                k = lab_base + lv - 1
            if cl == _CELL_MIXED and lv == 0:
                fx = min(max(px - x, 0.0), 1.0)
                fy = min(max(py - y, 0.0), 1.0)
                fz = min(max(pz - z, 0.0), 1.0)
                k = _table_index(flat, o, isy, isz, _U1, fx, fy, fz, lab_end)
            if memb[k] <= 0.0:
                continue
            al = alpha_r[k]
            if al > 0.0:
                tr *= 1.0 - al
                if tr < half:
                    break


@njit(parallel=True, cache=True)
def records_reached(data, aspect, index, mask, out):
    """``index | code << 16`` per voxel, the code only at the corners of cells in ``mask``'s blocks.

    :func:`_numba_grid.records_where`'s records where a render can shade
    (:func:`reached_blocks`); every other voxel gets the zero-gradient code.  Every voxel is
    written with that code first (one pass, no code), then the corners of the cells of each
    marked block (voxels ``4 b .. 4 b + 4`` per axis, the voxels whose cells ``v - 1`` or
    ``v`` lie in block ``b``) get theirs: a render's marked blocks are a thin shell (the
    1024 x 1024 x 904 CT: testing 8 blocks per voxel took 0.15 s a brick).  Neighbouring
    blocks share a layer of voxels, written with the same value.
    """
    nz, ny, nx = data.shape
    ax, ay, az = aspect[0], aspect[1], aspect[2]
    zero = np.uint32(_ZERO_CODE) << np.uint32(16)
    for zz in prange(nz):
        z = np.int64(zz)
        for y in range(ny):
            for x in range(nx):
                out[z, y, x] = np.uint32(index[z, y, x]) | zero
    mz, my, mx = mask.shape
    for bz in prange(mz):
        z0 = np.int64(bz) * _BLOCK
        for by in range(my):
            y0 = by * _BLOCK
            for bx in range(mx):
                if not mask[bz, by, bx]:
                    continue
                x0 = bx * _BLOCK
                for z in range(z0, min(z0 + _BLOCK + 1, nz)):
                    for y in range(y0, min(y0 + _BLOCK + 1, ny)):
                        for x in range(x0, min(x0 + _BLOCK + 1, nx)):
                            code = _code(data, z, y, x, nz, ny, nx, ax, ay, az)
                            out[z, y, x] = np.uint32(index[z, y, x]) | (
                                np.uint32(code) << np.uint32(16)
                            )


@njit(cache=True)
def crossing(order, chunk_ptr, j0, j1, out_order, out_ptr, out_runs):
    """Keep the rays of ``order``'s chunks with ``j1 > j0``, chunk by chunk (no empty chunks).

    Writes the rays to ``out_order``, the chunks' bounds to ``out_ptr`` and each kept chunk's
    samples (``sum(j1 - j0)``) to ``out_runs``; returns ``(rays, chunks)`` kept.
    """
    m = 0
    nc = 0
    out_ptr[0] = 0
    for c in range(len(chunk_ptr) - 1):
        first = m
        runs = 0
        for i in range(chunk_ptr[c], chunk_ptr[c + 1]):
            r = order[i]
            if j1[r] > j0[r]:
                out_order[m] = r
                m += 1
                runs += j1[r] - j0[r]
        if m > first:
            out_runs[nc] = runs
            nc += 1
            out_ptr[nc] = m
    return m, nc


@njit(cache=True)
def any_alive(j0, j1, st, ert):
    """Return whether a ray with samples in ``[j0, j1)`` has ``st[r, 3] >= ert``."""
    for r in range(len(j0)):  # noqa: SIM110 (numba: a loop that stops at the first)
        if j1[r] > j0[r] and st[r, 3] >= ert:
            return True
    return False
