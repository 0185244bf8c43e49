"""numba kernels of the ray-analysis engine (see :mod:`dvr_perception.rays.engine`).

Kernels, parallel over chunks of image tiles (:func:`dvr_perception.rays.engine.ray_order`):

* :func:`walk` marches every ray through the voxel records (table index, and VTK's encoded
  normal when shading) at VTK's sample positions and composites it until early ray
  termination; :func:`_tail` goes on to the end of the ray reading only the compact table
  index, since ``present`` and the occlusion-free ``assigned`` need every sample.  Both look
  up each sample's block of 4^3 cells in :func:`_grid.block_map` first (small enough to stay
  in the processor's cache): far from anything the ray jumps by whole blocks.  Otherwise the
  block's bits in :func:`_grid.block_occupancy` (8 bytes per block, also cached) say whether
  the sample's cell is empty: it is passed over without reading the cell map, which does not
  stay in the cache.  Otherwise the sample's cell class in :func:`_grid.cell_map`: a plateau
  cell gives the table entry without interpolating the 8 corners.
  With ``build`` the walk packs one cache entry per sample with membership > 0 (table index,
  sample index, shading and curvature) into its chunk's region.  Without it (and unless
  ``exact``) :func:`_tail` skips what cannot change a result (DECISIONS D8): a structure whose
  ``assigned`` has saturated, and, once the transmittance at the importances is below early
  ray termination, blocks whose cells reach only saturated structures
  (:func:`_grid.structure_blocks`).
* Shading (:func:`_shade_at`) is VTK's: the shading-table entries of the 8 corners' normal codes
  are interpolated trilinearly (lit diffuse cosine and specular power term, stored per entry as
  uint16 ``round(x * 65534)``; materials, colours and opacities are applied at compositing).
* :func:`composite` re-composites from cache entries (no volume access except below).
* Shading and curvature of entries the walk's compositing did not reach (behind early ray
  termination) are marked unset (65535, curvature -1) and computed lazily (:func:`_fill`)
  the first time a re-evaluation reaches them; :func:`invalidate` marks all shading so after
  a change of light, :func:`invalidate_structures` only some structures' after a change of
  their specular powers.
  Sample positions are recomputed bit-identically from the sample index (no fp contraction).
* :func:`segments` sets up every pixel's ray; :func:`compact` packs the entries in pixel order.

Both compositing paths use the same quantised shading and the same update, so an
analysis composited from the cache equals one composited during the walk.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic, overload

_ir = cgutils.ir  # numba's LLVM IR builder (llvmlite), for _prefetch

__all__ = [
    "compact",
    "composite",
    "invalidate",
    "invalidate_structures",
    "segments",
    "segments_at",
    "walk",
    "walk_variants",
]

# VTK's fixed-point trilinear weights sum to 32765/32768 and the index is rounded up.
_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0
#: fastmath without contraction or reassociation: sample positions are bit-identical wherever
#: they are recomputed (walk, lazy normal fill), so cached and fresh results agree exactly.
_FM = {"nnan", "ninf", "nsz", "arcp", "afn"}
_U1 = np.uint64(1)
_U16 = np.uint32(16)
_MASK = np.uint32(0xFFFF)
#: Shading factors are stored as uint16 ``round(x * 65534)``; ``_UNSET`` = not yet computed.
_IQS = 1.0 / 65534.0
#: Cell classes (= ``_grid.CELL_EMPTY`` / ``CELL_MIXED``, tested); ``1 + s`` is ``s``'s plateau.
_CELL_EMPTY = 0
_CELL_MIXED = 255
#: Side of :func:`_grid.block_map`'s blocks (= ``_grid.BLOCK``, tested; ``>> 2`` below).
_BLOCK = 4


def _flat(a):
    """Return ``a`` as one dimension (a view of a C-contiguous array); numba inlines a twin.

    In numba, ``a.reshape(a.size)`` calls a C helper (about 20 ns): several times per ray
    (:func:`_walk_ray`, :func:`_tail`) that is a few per cent of the walk.  The overload
    below makes the same view in a few instructions; the CUDA twins
    (:mod:`dvr_perception.rays._cuda_kernels`) and the simulator use this Python.
    """
    return a.reshape(a.size)


@intrinsic
def _flat_view(typingctx, arr):
    """Return a 1-D view of the C-contiguous array ``arr`` (same data, owner and item size)."""
    if not isinstance(arr, types.Array) or arr.layout != "C":
        return None
    ret = arr.copy(ndim=1, layout="C")

    def codegen(context, builder, sig, args):
        src = context.make_array(sig.args[0])(context, builder, value=args[0])
        dst = context.make_array(sig.return_type)(context, builder)
        dims = cgutils.unpack_tuple(builder, src.shape)
        n = dims[0]
        for d in dims[1:]:
            n = builder.mul(n, d)
        size = src.itemsize
        context.populate_array(
            dst, data=src.data, shape=cgutils.pack_array(builder, [n]),
            strides=cgutils.pack_array(builder, [size]), itemsize=size, meminfo=src.meminfo,
            parent=src.parent,
        )  # fmt: skip
        res = dst._getvalue()
        if context.enable_nrt:  # a new reference to the same memory
            context.nrt.incref(builder, sig.return_type, res)
        return res

    return ret(arr), codegen


@overload(_flat, inline="always")
def _flat_numba(a):
    if isinstance(a, types.Array) and a.layout == "C":
        return lambda a: _flat_view(a)
    return lambda a: a.reshape(a.size)


def _no_prefetch(arr, idx):
    """Do nothing: :func:`_prefetch` of the CUDA twins (:mod:`_cuda_kernels`)."""


@intrinsic
def _prefetch(typingctx, arr, idx):
    """Ask the processor to load ``arr[idx]`` (1-D C array) into its caches; nothing else.

    LLVM's ``prefetch`` (read, kept in every cache level): no result changes, only when the
    memory arrives.  The walk asks for a sample's cell class and corners two samples ahead,
    so they come from memory while it classifies, shades and composites the samples before
    (lobster -5 %, bonsai -3 % of a 512^2 render on one thread).
    """
    if not isinstance(arr, types.Array) or arr.layout != "C" or arr.ndim != 1:
        return None

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, value=args[0])
        p8 = builder.bitcast(builder.gep(ary.data, [args[1]]), _ir.IntType(8).as_pointer())
        i32 = _ir.IntType(32)
        name = "llvm.prefetch.p0" if str(p8.type) == "ptr" else "llvm.prefetch.p0i8"
        fnty = _ir.FunctionType(_ir.VoidType(), [p8.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, name)
        builder.call(fn, [p8, i32(0), i32(3), i32(1)])  # read, keep, data
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


def _dense_at(curv, z, y, x):
    """``curv[z, y, x]`` of a dense ``|H|`` volume."""
    return curv[z, y, x]


def _paged_at(curv, z, y, x):
    """``|H|`` at voxel ``(z, y, x)`` of 8^3 pages ``curv = (index, pages)``."""
    index, pages = curv
    p = index[z >> 3, y >> 3, x >> 3]
    if p < 0:
        return np.float32(0.0)
    return pages[p, z & 7, y & 7, x & 7]


def _curv_at(curv, z, y, x):
    """``|H|`` at voxel ``(z, y, x)``: ``curv`` dense ``(Z, Y, X)`` or pages ``(index, pages)``.

    The walk of the whole volume reads pages
    (:class:`~dvr_perception.rays.curvature_field.CurvaturePages`), a brick its dense piece;
    numba picks the reader by ``curv``'s type.
    """
    if isinstance(curv, tuple):
        return _paged_at(curv, z, y, x)
    return _dense_at(curv, z, y, x)


@overload(_curv_at, inline="always")
def _curv_at_numba(curv, z, y, x):
    if isinstance(curv, types.BaseTuple):
        return _paged_at
    return _dense_at


@njit(cache=True, fastmath=_FM, inline="always")
def _jump_scale(bx, by, bz, step):
    """Return the samples per voxel of advance along the ray's fastest axis (empty-space jumps)."""
    m = max(abs(bx), abs(by), abs(bz)) * step
    return 1.0 / m if m > 0.0 else 1e9


_UNSET = 65535


@njit(parallel=True, cache=True)
def segments(cam, a, b, t_first, nsteps):
    """Per-pixel rays and sample ranges; the numba twin of ``_grid.ray_segments``.

    ``cam`` is :func:`dvr_perception.rays._grid.camera_pack` output.
    """
    width = int(cam[14])
    height = int(cam[15])
    for row in prange(height):
        for col in range(width):
            r = row * width + col
            _segment(cam, row, col, r, a, b, t_first, nsteps)


@njit(parallel=True, cache=True, nogil=True)
def segments_at(cam, rays, a, b, t_first, nsteps):
    """:func:`segments` of the flat pixel indices ``rays`` only: row ``i`` is ray ``rays[i]``.

    Each row equals the whole image's row of that pixel to the bit (the same arithmetic), so
    a walk of a few rays (the view without an enclosing layer, DECISIONS D7) sets up only them.
    """
    width = int(cam[14])
    m = rays.shape[0]
    nchunk = min(max(m // 256, 1), 64)
    for c in prange(nchunk):
        for i in range(c * m // nchunk, (c + 1) * m // nchunk):
            p = rays[i]
            _segment(cam, p // width, p % width, i, a, b, t_first, nsteps)


@njit(cache=True, nogil=True)
def _segment_of(cam, p, a, b, t_first, nsteps):
    """:func:`_segment` of flat pixel ``p``, into row 0.

    Compiled alone: it is called from kernels with fastmath, whose flags must not reach these
    operations, so the rays stay the bits of :func:`segments`.
    """
    width = int(cam[14])
    _segment(cam, p // width, p % width, 0, a, b, t_first, nsteps)


@njit(cache=True, inline="always")
def _segment(cam, row, col, r, a, b, t_first, nsteps):
    """Set up pixel ``(row, col)``'s ray in row ``r`` of ``a``, ``b``, ``t_first``, ``nsteps``."""
    width = int(cam[14])
    height = int(cam[15])
    par = cam[13] != 0.0
    half = cam[12]
    aspect = cam[14] / cam[15]
    step = cam[27]
    lo = cam[28]
    ys = 1.0 - 2.0 * (row + 0.5) / height
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
def _shade_at(volf, o, isy, isz, fx, fy, fz, tab, s, shift):
    """VTK's shading of a sample: the 8 corners' table entries, trilinearly mixed.

    ``volf`` holds ``index | code << 16`` per voxel (``shift`` 16; or bare codes, 0), ``o``
    is the cell's first corner and
    ``tab`` is :func:`dvr_perception.rays._tables.shading_table`.  Returns the lit diffuse
    cosine and the specular power term, both tabulated and returned as ``round(x * 65534)``
    (uint16, as stored in the cache; 65535 marks "not yet computed").
    """
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    o1 = o + isy
    o2 = o + isz
    o3 = o2 + isy
    c0 = volf[o] >> shift
    c1 = volf[o + _U1] >> shift
    c2 = volf[o1] >> shift
    c3 = volf[o1 + _U1] >> shift
    c4 = volf[o2] >> shift
    c5 = volf[o2 + _U1] >> shift
    c6 = volf[o3] >> shift
    c7 = volf[o3 + _U1] >> shift
    w0 = gz * gy * gx
    w1 = gz * gy * fx
    w2 = gz * fy * gx
    w3 = gz * fy * fx
    w4 = fz * gy * gx
    w5 = fz * gy * fx
    w6 = fz * fy * gx
    w7 = fz * fy * fx
    dl = (
        w0 * tab[s, c0, 0] + w1 * tab[s, c1, 0] + w2 * tab[s, c2, 0] + w3 * tab[s, c3, 0]
        + w4 * tab[s, c4, 0] + w5 * tab[s, c5, 0] + w6 * tab[s, c6, 0] + w7 * tab[s, c7, 0]
    )  # fmt: skip
    sp = (
        w0 * tab[s, c0, 1] + w1 * tab[s, c1, 1] + w2 * tab[s, c2, 1] + w3 * tab[s, c3, 1]
        + w4 * tab[s, c4, 1] + w5 * tab[s, c5, 1] + w6 * tab[s, c6, 1] + w7 * tab[s, c7, 1]
    )  # fmt: skip
    return np.uint16(min(int(dl + 0.5), 65534)), np.uint16(min(int(sp + 0.5), 65534))


@njit(cache=True, fastmath=_FM, inline="always")
def _table_index(flat, o, sy, sz, one, fx, fy, fz, last):
    """Table entry of a sample: VTK's trilinear index of the cell at flat offset ``o``.

    ``flat`` holds the table index in its low 16 bits (voxel records or the compact index),
    ``sy``/``sz`` are the row and plane strides and ``one`` is 1 of the offsets' type;
    ``fx, fy, fz`` the sample's place in the cell.  Rounded as VTK's fixed-point weights
    round, and at most ``last``.
    """
    gx = 1.0 - fx
    gy = 1.0 - fy
    o1 = o + sy
    o2 = o + sz
    o3 = o2 + sy
    f = (
        (1.0 - fz) * (gy * (gx * (flat[o] & _MASK) + fx * (flat[o + one] & _MASK))
                      + fy * (gx * (flat[o1] & _MASK) + fx * (flat[o1 + one] & _MASK)))
        + fz * (gy * (gx * (flat[o2] & _MASK) + fx * (flat[o2 + one] & _MASK))
                + fy * (gx * (flat[o3] & _MASK) + fx * (flat[o3 + one] & _MASK)))
    )  # fmt: skip
    return min(int(f * _W_SCALE + _W_BIAS), last)


@njit(cache=True, fastmath=_FM, inline="always")
def _entry(cl, volf, o, isy, isz, px, py, pz, fx, fy, fz, rep, lab, lab_base, lab_end, ox, oy, oz):
    """Table entry of a sample in a cell of class ``cl`` (not empty) at flat offset ``o``.

    A plateau cell's entry is its structure's ``rep``; in a mixed cell, the label of the
    sample's nearest voxel (``lab``, voxel ``(ox, oy, oz)`` at ``lab[0, 0, 0]``) where it
    has one, else VTK's trilinear index (:func:`_table_index`, at most ``lab_end``).  The
    one classification of :func:`_walk_ray` and :func:`walk_variants`.
    """
    if cl != _CELL_MIXED:
        return rep[cl - 1]
    if lab_base >= 0:
        lv = lab[int(pz + 0.5) - oz, int(py + 0.5) - oy, int(px + 0.5) - ox]
        if lv != 0:
            return lab_base + lv - 1
    return _table_index(volf, o, isy, isz, _U1, fx, fy, fz, lab_end)


@njit(cache=True, fastmath=_FM, inline="always")
def _block_skip(blocks, x, y, z, binv):
    """Return how many samples a ray may skip from cell ``(x, y, z)`` (0: look at the cell).

    A block at empty-space distance ``d > 1`` has only empty blocks within ``d - 1`` blocks:
    ``binv`` (samples per block of advance along the ray's fastest axis) times ``d - 1``.
    """
    d = blocks[z >> 2, y >> 2, x >> 2]
    return max(int((d - 1) * binv), 1) if d > 1 else 0


@njit(cache=True, fastmath=_FM, inline="always")
def _occupied(occ, ob, x, y, z):
    """Whether cell ``(x, y, z)`` (in block ``ob`` of :func:`_grid.block_occupancy`) is not empty.

    The same answer as ``cells[z, y, x] != CELL_EMPTY`` from 8 bytes per block, which stay in
    the processor's cache where the cell map does not.
    """
    return (occ[ob] >> np.uint64(((z & 3) << 4) | ((y & 3) << 2) | (x & 3))) & _U1 != 0


@njit(cache=True, fastmath=_FM, inline="always")
def _sample_at(j, t_first, step, ax, ay, az, bx, by, bz, nx, ny, nz):
    """Position of sample ``j`` in voxel coordinates and its cell (clamped to the grid).

    The one place positions are computed, so every kernel gets them bit-identical.
    """
    t = t_first + j * step
    px = ax + t * bx
    py = ay + t * by
    pz = az + t * bz
    x = min(max(int(px), 0), nx - 2)
    y = min(max(int(py), 0), ny - 2)
    z = min(max(int(pz), 0), nz - 2)
    return px, py, pz, x, y, z


@njit(cache=True, fastmath=_FM, inline="always")
def _block_exit(j, n, t_first, step, ax, ay, az, bx, by, bz, x0, y0, z0):
    """Return the sample to look at next after sample ``j``, in the block of cells from ``x0``.

    The ray leaves the box of cells ``[x0, x0 + 4)`` (likewise y, z) where it first crosses one
    of its faces moved ``1e-6`` voxel inwards (far more than the rounding of a position);
    every sample up to that point lies inside the box, so the one after it is the first that
    may not, and no sample of another block is passed over.  At least ``j + 1``, at most
    ``n``.
    """
    t_out = 1e300
    for i in range(3):
        ai = ax if i == 0 else (ay if i == 1 else az)
        bi = bx if i == 0 else (by if i == 1 else bz)
        c0 = x0 if i == 0 else (y0 if i == 1 else z0)
        if bi > 0.0:
            t_out = min(t_out, (c0 + _BLOCK - 1e-6 - ai) / bi)
        elif bi < 0.0:
            t_out = min(t_out, (c0 + 1e-6 - ai) / bi)
    f = (t_out - t_first) / step
    if f >= n:
        return n
    return max(j + 1, int(f) + 1)  # f < 0: below j + 1 anyway


@njit(cache=True, fastmath=_FM, inline="always")
def _tail(r, tix, cells, blocks, occ, tail_maps, lab, lab_base, ax, ay, az, bx, by, bz, t_first,
          j, n, step, shade, has_curv, build, base, cnt, walked, bits, asg, out, ti, ert,
          geo):  # fmt: skip
    """Walk the rest of a ray after early ray termination: only each sample's table index.

    Accumulates the occlusion-free ``asg``, the ``present`` bits and the transmittance ``ti`` at
    the importance opacities (until it falls below ``ert``) and, with ``build``, writes
    cache entries whose shading and curvature are left unset.  ``tix`` is the compact table
    index volume (uint8 when the table has at most 256 entries): a quarter of the memory
    traffic of the voxel records.  Far from anything the ray jumps by whole blocks of the
    small block map (:func:`_grid.block_map`, which stays in the processor's cache).
    Otherwise every sample is looked at, with few branches: a plateau or empty cell's class
    (:func:`_grid.cell_map`) gives the table entry through ``kmap``, a mixed cell's entry
    is interpolated, and an entry outside every structure counts for the spare structure
    ``len(asg) - 1`` (opacity 0; its row of ``asg`` is dropped later; ``t_bit`` holds each
    entry's ``present`` bit, 0 for the spare).  Looking at empty and plateau samples one by
    one costs less than jumping over the short runs that noisy data have (cthead: 25 %
    less time for whole rays, the same sums to the last bit).

    ``tail_maps`` ends with ``smask``, ``sdist`` and ``cap``.  ``cap`` finite (the skipping
    walk, never with ``build``): a structure whose ``asg`` reaches ``cap`` has saturated on
    this ray and keeps ``cap``; once ``ti < ert`` a block whose ``smask``
    (:func:`_grid.structure_blocks`: the structures its cells can reach) holds only saturated
    structures is jumped like an empty one, as far as ``sdist``
    (:func:`_grid.structure_distances`) says no block reaches a structure still unsaturated,
    and the ray stops when every structure has saturated.  Nothing the walk
    returns changes but ``asg`` above ``cap`` (which is ``min(asg, cap)``) and ``walked``.
    """
    kmap, tids, t_alpha, t_bit, smask, sdist, cap = tail_maps
    c_lut, c_j, c_sh, c_curv = out
    spare = asg.shape[0] - 1
    lab_end = (lab_base if lab_base >= 0 else len(tids) - 1) - 1
    gnx, gny, gnz, ox, oy, oz = geo
    ny, nx = tix.shape[1], tix.shape[2]
    tf = _flat(tix)
    cf = _flat(cells)
    bf = _flat(blocks)
    of = _flat(occ)
    bnx = blocks.shape[2]
    bnxy = blocks.shape[1] * bnx
    nxy = nx * ny
    binv = _jump_scale(bx, by, bz, step) * _BLOCK
    skipping = cap < 1e299 and not build
    sf = _flat(smask)
    sd = _flat(sdist)
    nblk = blocks.size
    has_dist = (sdist.shape[1] == blocks.shape[0] and sdist.shape[2] == blocks.shape[1]
                and sdist.shape[3] == blocks.shape[2])  # fmt: skip
    every = (np.uint64(1) << np.uint64(spare)) - np.uint64(1)
    sat = np.uint64(0)
    if skipping:
        for s in range(spare):
            if asg[s, r] >= cap:
                sat |= np.uint64(1) << np.uint64(s)
    while j < n:
        if skipping and ti < ert and sat == every:
            break  # every structure has saturated: nothing further can change a result
        px, py, pz, x, y, z = _sample_at(j, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz)
        walked += 1
        lx = x - ox
        ly = y - oy
        lz = z - oz
        ob = (lz >> 2) * bnxy + (ly >> 2) * bnx + (lx >> 2)
        d = bf[ob]
        if d > 1:
            j += max(int((d - 1) * binv), 1)
            continue
        if skipping and ti < ert and (np.uint64(sf[ob]) & ~sat) == 0:
            if has_dist:  # how far no block can reach a structure still unsaturated
                dmin = 255
                for q in range(spare):
                    if (sat >> np.uint64(q)) & np.uint64(1) == 0:
                        dmin = min(dmin, sd[q * nblk + ob])
                if dmin > 1:
                    j += max(int((dmin - 1) * binv), 1)
                    continue
            j = _block_exit(j, n, t_first, step, ax, ay, az, bx, by, bz, ((lx >> 2) << 2) + ox,
                            ((ly >> 2) << 2) + oy, ((lz >> 2) << 2) + oz)  # fmt: skip
            continue
        if not _occupied(of, ob, lx, ly, lz):
            j += 1  # an empty cell: the spare entry, which adds nothing (opacity 0, no bit)
            continue
        o = lz * nxy + ly * nx + lx
        cl = cf[o]
        k = kmap[cl]
        if cl == _CELL_MIXED:
            lv = 0
            if lab_base >= 0:
                lv = lab[int(pz + 0.5) - oz, int(py + 0.5) - oy, int(px + 0.5) - ox]
                k = lab_base + lv - 1
            if lv == 0:
                fx = min(max(px - x, 0.0), 1.0)
                fy = min(max(py - y, 0.0), 1.0)
                fz = min(max(pz - z, 0.0), 1.0)
                k = _table_index(tf, o, nx, nxy, 1, fx, fy, fz, lab_end)
        s = tids[k]
        if skipping:
            if s != spare and (sat >> np.uint64(s)) & np.uint64(1) == 0:
                v = asg[s, r] + t_alpha[k]
                if v >= cap:
                    v = cap
                    sat |= np.uint64(1) << np.uint64(s)
                asg[s, r] = v
        else:
            asg[s, r] += t_alpha[k]
        if ti >= ert:
            ti *= 1.0 - t_alpha[k]
        bits |= t_bit[k]
        if build and s != spare:
            e = base + cnt
            c_lut[e] = k
            c_j[e] = j
            if shade:
                c_sh[e, 0] = _UNSET
            if has_curv:
                c_curv[e] = -1.0
            cnt += 1
        j += 1
    return cnt, walked, bits, ti


@njit(cache=True, fastmath=_FM, inline="always")
def _walk_ray(
    r, vol, maps, curv, a, b, t_first, jr, step, ids, memb, alpha_r, alpha_w, col, light, tab,
    shade, has_curv, build, tail, base, ert, vis, asg, sta, sbits, geo, out,
):  # fmt: skip
    """Walk one ray, compositing until early ray termination.

    ``maps`` is ``(tix, cells, blocks, occ, rep, lab, lab_base, tail_maps)`` (see
    :func:`walk` and :func:`_tail`: with a finite ``cap`` every ``asg`` stays at most ``cap``;
    one tuple because a call with more than 30 arguments becomes ``*args``, which numba cannot
    inline).

    ``vol`` holds the table index per voxel (low 16 bits) and, when shading, the normal code
    (high 16 bits).  ``build``: also write one cache entry per sample with membership
    (table index, sample index, shading and curvature; the last two marked "not yet computed"
    (-1) for samples that compositing did not reach).

    The ray walks its samples ``jr = (j0, j1)`` and continues its state: row ``r`` of
    ``sta`` holds ``cr, cg, cb, tr, ti, num, den`` (premultiplied
    colour, transmittance, transmittance at the importances, curvature numerator and weight),
    ``sbits[r]`` the present bits; ``vis`` and ``asg`` are added to.  A whole ray starts from
    ``(0, 0, 0, 1, 1, 0, 0)`` and no bits at ``(0, n)``; a brick of a
    bricked analysis (:mod:`dvr_perception.rays.bricks`) walks the samples in its cells and
    hands the state on.  ``geo = (nx, ny, nz, ox, oy, oz)``: the whole volume's voxel counts
    (sample positions and cells are the whole volume's, so every brick samples where the whole
    walk does) and the global index of ``vol[0, 0, 0]`` (all volumes here are the brick's).

    Returns ``(entries, samples walked)``; the state's ``ti`` is the ray's transmittance
    at the importance opacities ``alpha_w`` with early ray termination (``1 - ti`` is the
    accumulated opacity of the ray rendered at the importances).
    """
    c_lut, c_j, c_sh, c_curv = out
    tix, cells, blocks, occ, rep, lab, lab_base, tail_maps = maps
    lab_end = (lab_base if lab_base >= 0 else len(ids)) - 1
    cap = tail_maps[6]
    gnx, gny, gnz, ox, oy, oz = geo
    ny, nx = vol.shape[1], vol.shape[2]
    volf = _flat(vol)
    clf = _flat(cells)
    bf = _flat(blocks)
    of = _flat(occ)
    bnx = blocks.shape[2]
    bnxy = blocks.shape[1] * bnx
    isy = np.uint64(nx)
    nxy = nx * ny
    isz = np.uint64(nxy)
    ka, kd, ks = light[0], light[1], light[2]
    ax, ay, az = a[r, 0], a[r, 1], a[r, 2]
    bx, by, bz = b[r, 0], b[r, 1], b[r, 2]
    cr = sta[r, 0]
    cg = sta[r, 1]
    cb = sta[r, 2]
    tr = sta[r, 3]
    ti = sta[r, 4]
    num = sta[r, 5]
    den = sta[r, 6]
    bits = sbits[r]
    cnt = 0
    walked = 0
    alive = tr >= ert
    j, n = jr
    binv = _jump_scale(bx, by, bz, step) * _BLOCK
    while j < n and alive:
        px, py, pz, x, y, z = _sample_at(j, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz)
        walked += 1
        lx = x - ox
        ly = y - oy
        lz = z - oz
        ob = (lz >> 2) * bnxy + (ly >> 2) * bnx + (lx >> 2)
        d = bf[ob]
        if d > 1:  # as _block_skip
            j += max(int((d - 1) * binv), 1)
            continue
        if not _occupied(of, ob, lx, ly, lz):  # an empty cell
            j += 1
            continue
        o = np.uint64(lz * nxy + ly * nx + lx)
        cl = clf[o]
        if j + 2 < n:  # a sample ahead: its cell and corners are on their way meanwhile
            _, _, _, x2, y2, z2 = _sample_at(j + 2, t_first, step, ax, ay, az, bx, by, bz, gnx,
                                             gny, gnz)  # fmt: skip
            o2 = np.uint64((z2 - oz) * nxy + (y2 - oy) * nx + (x2 - ox))
            _prefetch(clf, o2)
            _prefetch(volf, o2)
            _prefetch(volf, o2 + isz)
        fx = min(max(px - x, 0.0), 1.0)
        fy = min(max(py - y, 0.0), 1.0)
        fz = min(max(pz - z, 0.0), 1.0)
        k = _entry(cl, volf, o, isy, isz, px, py, pz, fx, fy, fz, rep, lab, lab_base, lab_end,
                   ox, oy, oz)  # fmt: skip
        if memb[k] <= 0.0:
            j += 1
            continue
        s = ids[k]
        bits |= np.uint32(1) << np.uint32(s)
        asg[s, r] = min(asg[s, r] + alpha_w[k], cap)  # cap: see _tail (1e300: no cap)
        if ti >= ert:
            ti *= 1.0 - alpha_w[k]
        e = base + cnt
        if build:
            c_lut[e] = k
            c_j[e] = j
            cnt += 1
        j += 1
        al = alpha_r[k]
        if al <= 0.0:
            if build:
                if shade:
                    c_sh[e, 0] = _UNSET
                if has_curv:
                    c_curv[e] = -1.0
            continue
        dfac = 1.0
        spec = 0.0
        if shade:
            dl, sp = _shade_at(volf, o, isy, isz, fx, fy, fz, tab, s, _U16)
            if build:
                c_sh[e, 0] = dl
                c_sh[e, 1] = sp
            dfac = ka[s] + kd[s] * (dl * _IQS)
            spec = ks[s] * (sp * _IQS)
        hc = 0.0
        if has_curv:
            hc = _curv_at(curv, int(pz + 0.5) - oz, int(py + 0.5) - oy, int(px + 0.5) - ox)
            if build:
                c_curv[e] = hc
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
    if j < n and tail:
        cnt, walked, bits, ti = _tail(
            r, tix, cells, blocks, occ, tail_maps, lab, lab_base, ax, ay, az, bx, by, bz, t_first,
            j, n, step, shade, has_curv, build, base, cnt, walked, bits, asg, out, ti, ert, geo,
        )  # fmt: skip
    sta[r, 0] = cr
    sta[r, 1] = cg
    sta[r, 2] = cb
    sta[r, 3] = tr
    sta[r, 4] = ti
    sta[r, 5] = num
    sta[r, 6] = den
    sbits[r] = bits
    return cnt, walked


@njit(cache=True, fastmath=_FM, inline="always")
def _fill(e, j, ax, ay, az, bx, by, bz, t_first, step, vol, curv, tab, s, shade, has_curv,
          c_sh, c_curv, geo, shift):  # fmt: skip
    """Compute entry ``e``'s shading and curvature from its sample index, as the walk would.

    ``geo``: as in :func:`_walk_ray` (the whole volume's voxel counts, ``vol``'s offset);
    ``vol`` holds the normal code ``>> shift``: voxel records (16) or bare codes (0).
    """
    gnx, gny, gnz, ox, oy, oz = geo
    ny, nx = vol.shape[1], vol.shape[2]
    px, py, pz, x, y, z = _sample_at(j, t_first, step, ax, ay, az, bx, by, bz, gnx, gny, gnz)
    if shade:
        volf = _flat(vol)
        fx = min(max(px - x, 0.0), 1.0)
        fy = min(max(py - y, 0.0), 1.0)
        fz = min(max(pz - z, 0.0), 1.0)
        o = np.uint64((z - oz) * (nx * ny) + (y - oy) * nx + (x - ox))
        dl, sp = _shade_at(volf, o, np.uint64(nx), np.uint64(nx * ny), fx, fy, fz, tab, s, shift)
        c_sh[e, 0] = dl
        c_sh[e, 1] = sp
    if has_curv:
        c_curv[e] = _curv_at(curv, int(pz + 0.5) - oz, int(py + 0.5) - oy, int(px + 0.5) - ox)


@njit(cache=True, fastmath=_FM, inline="always")
def _composite_ray(
    r, e0, cnt, c_lut, c_j, c_sh, c_curv, a, b, t_first, step, vol, curv, ids, alpha_r, col,
    light, tab, shade, has_curv, ert, vacc, chunk, bg, rgba, image, acc, vis, cimg,
):  # fmt: skip
    """Front-to-back compositing of ray ``r``'s entries with early ray termination.

    Shading and curvature of entries reached for the first time are computed and stored.
    Accumulates the visible shares in float64 (``vacc[chunk]``: a slot per structure), writes
    rgba, the image over the background ``bg``, accumulated opacity, visible shares and
    curvature as float32, so no separate finishing pass is needed.
    """
    nstruct = vis.shape[0]
    for s in range(nstruct):
        vacc[chunk, s] = 0.0
    ka, kd, ks = light[0], light[1], light[2]
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
        # shading and curvature are set together (walk, _fill); only a change of light unsets
        # shading alone, so with shading on its marker is the one to test
        if (c_sh[e, 0] == _UNSET) if shade else (has_curv and c_curv[e] < 0.0):
            nz, ny, nx = vol.shape
            _fill(e, c_j[e], a[r, 0], a[r, 1], a[r, 2], b[r, 0], b[r, 1], b[r, 2], t_first[r],
                  step, vol, curv, tab, s, shade, has_curv, c_sh, c_curv,
                  (nx, ny, nz, 0, 0, 0), _U16)  # fmt: skip
        dfac = 1.0
        spec = 0.0
        if shade:
            dfac = ka[s] + kd[s] * (c_sh[e, 0] * _IQS)
            spec = ks[s] * (c_sh[e, 1] * _IQS)
        w = al * tr
        vacc[chunk, s] += w
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
    al = np.float32(1.0 - tr)
    rgba[r, 3] = al
    acc[r] = al
    rgb = (np.float32(min(cr, 1.0)), np.float32(min(cg, 1.0)), np.float32(min(cb, 1.0)))
    for c in range(3):
        rgba[r, c] = rgb[c]
        image[r, c] = min(max(rgb[c] + (np.float32(1.0) - al) * bg[c], np.float32(0.0)), 1.0)
    cimg[r] = num / den if den > 0.0 else 0.0
    for s in range(nstruct):
        vis[s, r] = vacc[chunk, s]


@njit(parallel=True, cache=True, fastmath=_FM)
def walk(
    vol, tix, cells, blocks, occ, rep, lab, lab_base, kmap, tids, t_alpha, t_bit, smask, sdist, cap,
    curv, a, b,
    t_first, nsteps, step, order, chunk_ptr, nchunk, ids, memb, alpha_r, alpha_w, col, light, tab,
    shade, has_curv, build, tail, chunk_base, ert, rgba, vis, asg, present, cimg, c_lut, c_j,
    c_sh, c_curv, start, count, chunk_end, walked, aimp, state,
):  # fmt: skip
    """March and composite all rays; see the module docstring.  Outputs are flat per ray.

    ``aimp``: per ray, the accumulated opacity at the importance opacities (``1 - ti`` of
    :func:`_walk_ray`); ``state``: (R, 7) float64 scratch for :func:`_walk_ray`'s state.

    ``tix``, ``cells``, ``blocks`` and ``occ``: :func:`_grid.compact_index`,
    :func:`_grid.cell_map`, :func:`_grid.block_map` and :func:`_grid.block_occupancy`;
    ``order`` and ``chunk_ptr``: :func:`engine.ray_order`; ``tail``
    False (only without ``build``): stop every ray at early ray termination, as VTK does, so
    ``asg`` and ``present`` cover only the samples walked; ``rep``: a plateau table entry per
    structure; ``lab``: :func:`_grid.label_map` whose value ``v > 0``
    means table entry ``lab_base + v - 1`` (``lab_base`` -1: no label structures);
    ``kmap``, ``tids``, ``t_alpha`` and ``t_bit``: what :func:`_tail` reads
    (``asg`` has a spare last row for it, ``K + 1`` rows in all); ``smask``, ``sdist``
    (:func:`_grid.skip_maps`) and ``cap`` (:data:`_grid.SATURATION`, or 1e300 for the
    exact walk): the skipping walk behind early ray termination (:func:`_tail`).

    Chunk ``c`` (rays ``order[chunk_ptr[c]:chunk_ptr[c + 1]]``, whole tiles of pixels) packs
    their entries from ``chunk_base[c]`` on and records its end in ``chunk_end[c]``.
    """
    for c in prange(nchunk):
        # built here: a tuple holding a tuple of arrays cannot enter a parallel loop
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
        geo = (vol.shape[2], vol.shape[1], vol.shape[0], 0, 0, 0)
        e = chunk_base[c]
        for i in range(chunk_ptr[c], chunk_ptr[c + 1]):
            r = order[i]
            start[r] = e
            count[r] = 0
            for s in range(vis.shape[0]):
                vis[s, r] = 0.0
            for s in range(asg.shape[0]):
                asg[s, r] = 0.0
            if nsteps[r] == 0:
                rgba[r, 0] = 0.0
                rgba[r, 1] = 0.0
                rgba[r, 2] = 0.0
                rgba[r, 3] = 0.0
                cimg[r] = 0.0
                present[r] = 0
                walked[r] = 0
                aimp[r] = 0.0
                continue
            for q in range(7):
                state[r, q] = 1.0 if q == 3 or q == 4 else 0.0
            present[r] = 0
            cnt, wk = _walk_ray(
                r, vol, maps, curv, a, b, t_first[r], (0, np.int64(nsteps[r])), step, ids,
                memb, alpha_r, alpha_w, col, light, tab, shade, has_curv, build, tail, e, ert,
                vis, asg, state, present, geo, (c_lut, c_j, c_sh, c_curv),
            )  # fmt: skip
            rgba[r, 0] = min(state[r, 0], 1.0)
            rgba[r, 1] = min(state[r, 1], 1.0)
            rgba[r, 2] = min(state[r, 2], 1.0)
            rgba[r, 3] = 1.0 - state[r, 3]
            den = state[r, 6]
            cimg[r] = state[r, 5] / den if den > 0.0 else 0.0
            count[r] = cnt
            walked[r] = wk
            aimp[r] = 1.0 - state[r, 4]
            e += cnt
        chunk_end[c] = e


@njit(parallel=True, cache=True, fastmath=_FM, nogil=True)
def walk_variants(
    vol, cells, blocks, occ, rep, lab, lab_base, smask, sdist, cam, rays, step, want,
    ids, memb, alpha_v, visible, col, light, tab, shade, ert, rgba,
):  # fmt: skip
    """Image-only walks of rays with several opacity tables at once (``V`` variants).

    Row ``i`` is the ray of flat pixel ``rays[i]`` (set up here as :func:`segments` sets it
    up, ``cam``: :func:`dvr_perception.rays._grid.camera_pack`), wanted in variant ``v``
    where bit ``v`` of ``want[i]`` is set; ``alpha_v[v]`` is that
    variant's opacity table and ``visible[v]`` the bits of the structures it gives any
    opacity (``occ``: :func:`_grid.block_occupancy`, beside ``cells`` and ``blocks``).
    Every sample is read and classified once for all the variants of its ray (and
    shaded once, where one needs it); each variant composites front to back until its own
    early ray termination, the ray until the last has terminated.  ``rgba[v, i]`` (float32)
    is what :func:`walk` composites for that ray with that table (``occlusion_free=False``,
    as the engine's float32 result): the same arithmetic in the same order, so the same
    numbers to the bit.  Rows not wanted are not written.

    Samples that no variant still walking can see are passed over by whole blocks: blocks
    of empty space (:func:`_grid.block_map`) and blocks whose cells reach only structures
    of opacity 0 in every such variant (``smask``, :func:`_grid.structure_blocks`, as far as
    ``sdist``, :func:`_grid.structure_distances`, allows; a ``(k, 1, 1, 1)`` ``sdist``: to
    the block's exit).  They add nothing to any image: the view of an analysis without an
    enclosing layer (opacity 0, DECISIONS D7) does not step through that layer sample by
    sample.
    """
    m = want.shape[0]
    nvar = alpha_v.shape[0]
    nchunk = min(max(m // 16, 1), 64)
    nz, ny, nx = vol.shape
    for c in prange(nchunk):
        st = np.empty((nvar, 4), np.float64)  # per variant: cr, cg, cb, tr
        volf = _flat(vol)
        clf = _flat(cells)
        bf = _flat(blocks)
        of = _flat(occ)
        sf = _flat(smask)
        sd = _flat(sdist)
        nblk = blocks.size
        has_dist = (sdist.shape[1] == blocks.shape[0] and sdist.shape[2] == blocks.shape[1]
                    and sdist.shape[3] == blocks.shape[2])  # fmt: skip
        nstruct = sdist.shape[0]
        bnx = blocks.shape[2]
        bnxy = blocks.shape[1] * bnx
        isy = np.uint64(nx)
        nxy = nx * ny
        isz = np.uint64(nxy)
        lab_end = (lab_base if lab_base >= 0 else len(ids)) - 1
        ka, kd, ks = light[0], light[1], light[2]
        a = np.empty((1, 3))
        b = np.empty((1, 3))
        t_first = np.empty(1)
        nsteps = np.empty(1, np.int32)
        for i in range(c * m // nchunk, (c + 1) * m // nchunk):
            _segment_of(cam, rays[i], a, b, t_first, nsteps)
            alive = np.uint64(want[i])
            seen = np.uint64(0)
            for v in range(nvar):
                if (alive >> np.uint64(v)) & _U1:
                    st[v, 0] = 0.0
                    st[v, 1] = 0.0
                    st[v, 2] = 0.0
                    st[v, 3] = 1.0
                    seen |= np.uint64(visible[v])
            ax, ay, az = a[0, 0], a[0, 1], a[0, 2]
            bx, by, bz = b[0, 0], b[0, 1], b[0, 2]
            tf = t_first[0]
            n = np.int64(nsteps[0])
            binv = _jump_scale(bx, by, bz, step) * _BLOCK
            j = np.int64(0)
            while j < n and alive != 0:
                px, py, pz, x, y, z = _sample_at(j, tf, step, ax, ay, az, bx, by, bz, nx, ny, nz)
                ob = (z >> 2) * bnxy + (y >> 2) * bnx + (x >> 2)
                d = bf[ob]
                if d > 1:  # as _block_skip
                    j += max(int((d - 1) * binv), 1)
                    continue
                if (np.uint64(sf[ob]) & seen) == 0:  # only what no variant here can see
                    if has_dist:
                        dmin = 255
                        for q in range(nstruct):
                            if (seen >> np.uint64(q)) & _U1:
                                dmin = min(dmin, sd[q * nblk + ob])
                        if dmin > 1:
                            j += max(int((dmin - 1) * binv), 1)
                            continue
                    j = _block_exit(j, n, tf, step, ax, ay, az, bx, by, bz, (x >> 2) << 2,
                                    (y >> 2) << 2, (z >> 2) << 2)  # fmt: skip
                    continue
                if not _occupied(of, ob, x, y, z):  # an empty cell
                    j += 1
                    continue
                o = np.uint64(z * nxy + y * nx + x)
                cl = clf[o]
                fx = min(max(px - x, 0.0), 1.0)
                fy = min(max(py - y, 0.0), 1.0)
                fz = min(max(pz - z, 0.0), 1.0)
                k = _entry(cl, volf, o, isy, isz, px, py, pz, fx, fy, fz, rep, lab, lab_base,
                           lab_end, 0, 0, 0)  # fmt: skip
                j += 1
                if memb[k] <= 0.0:
                    continue
                s = ids[k]
                shaded = False
                dfac = 1.0
                spec = 0.0
                for v in range(nvar):
                    if ((alive >> np.uint64(v)) & _U1) == 0:
                        continue
                    al = alpha_v[v, k]
                    if al <= 0.0:
                        continue
                    if shade and not shaded:
                        dl, sp = _shade_at(volf, o, isy, isz, fx, fy, fz, tab, s, _U16)
                        dfac = ka[s] + kd[s] * (dl * _IQS)
                        spec = ks[s] * (sp * _IQS)
                        shaded = True
                    tr = st[v, 3]
                    w = al * tr
                    st[v, 0] += w * (col[s, 0] * dfac + spec)
                    st[v, 1] += w * (col[s, 1] * dfac + spec)
                    st[v, 2] += w * (col[s, 2] * dfac + spec)
                    tr *= 1.0 - al
                    st[v, 3] = tr
                    if tr < ert:
                        alive &= ~(_U1 << np.uint64(v))
                        seen = np.uint64(0)
                        for q in range(nvar):
                            if (alive >> np.uint64(q)) & _U1:
                                seen |= np.uint64(visible[q])
            wanted = np.uint64(want[i])
            for v in range(nvar):
                if (wanted >> np.uint64(v)) & _U1:
                    rgba[v, i, 0] = np.float32(min(st[v, 0], 1.0))
                    rgba[v, i, 1] = np.float32(min(st[v, 1], 1.0))
                    rgba[v, i, 2] = np.float32(min(st[v, 2], 1.0))
                    rgba[v, i, 3] = np.float32(1.0 - st[v, 3])


@njit(parallel=True, cache=True)
def compact(order, chunk_ptr, nchunk, start, count, dest, src_lut, src_j, src_sh, src_curv, lut,
            j_, sh, curv, shade, has_curv):  # fmt: skip
    """Copy every ray's entries from ``start[r]`` to ``dest[r]`` (rays in ``order``'s chunks)."""
    for c in prange(nchunk):
        for i in range(chunk_ptr[c], chunk_ptr[c + 1]):
            r = order[i]
            s0 = start[r]
            d0 = dest[r]
            for q in range(count[r]):
                lut[d0 + q] = src_lut[s0 + q]
                j_[d0 + q] = src_j[s0 + q]
                if shade:
                    sh[d0 + q, 0] = src_sh[s0 + q, 0]
                    sh[d0 + q, 1] = src_sh[s0 + q, 1]
                if has_curv:
                    curv[d0 + q] = src_curv[s0 + q]


@njit(parallel=True, cache=True, fastmath=_FM)
def composite(
    start, count, c_lut, c_j, c_sh, c_curv, a, b, t_first, step, vol, curv, order, chunk_ptr,
    nchunk, ids, alpha_r, col, light, tab, shade, has_curv, ert, out,
):  # fmt: skip
    """Front-to-back compositing of cached entries with early ray termination.

    No volume access except for shading and curvature of entries never reached before.
    ``out``: float32 (background, rgba, image, accumulated, visible, curvature), flat per ray.
    """
    bg, rgba, image, acc, vis, cimg = out  # unpacked here: no reference counting per ray
    vacc = np.empty((nchunk, max(vis.shape[0], 8)), np.float64)  # a cache line per chunk
    for c in prange(nchunk):
        for i in range(chunk_ptr[c], chunk_ptr[c + 1]):
            r = order[i]
            if count[r] == 0:  # nothing on this ray: background only
                for ch in range(4):
                    rgba[r, ch] = 0.0
                for ch in range(3):
                    image[r, ch] = min(max(bg[ch], np.float32(0.0)), np.float32(1.0))
                acc[r] = 0.0
                cimg[r] = 0.0
                for s in range(vis.shape[0]):
                    vis[s, r] = 0.0
                continue
            _composite_ray(
                r, start[r], count[r], c_lut, c_j, c_sh, c_curv, a, b, t_first, step, vol,
                curv, ids, alpha_r, col, light, tab, shade, has_curv, ert, vacc, c, bg,
                rgba, image, acc, vis, cimg,
            )  # fmt: skip


@njit(parallel=True, cache=True)
def invalidate(c_sh):
    """Mark every entry's shading as "not yet computed" (after a change of light)."""
    n = c_sh.shape[0]
    for ch in prange(64):
        for i in range(ch * n // 64, (ch + 1) * n // 64):
            c_sh[i, 0] = _UNSET


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


@njit(parallel=True, cache=True)
def invalidate_structures(c_sh, c_lut, ids, stale):
    """Mark the shading of the ``stale`` structures' entries as "not yet computed".

    After a change of specular powers alone (same light and view): the shading table changed
    only in those structures' rows, so the other entries keep theirs.  Entries outside every
    structure (``ids < 0``, never shaded) are marked too.
    """
    n = c_sh.shape[0]
    for ch in prange(64):
        for i in range(ch * n // 64, (ch + 1) * n // 64):
            s = ids[c_lut[i]]
            if s < 0 or stale[s]:
                c_sh[i, 0] = _UNSET
