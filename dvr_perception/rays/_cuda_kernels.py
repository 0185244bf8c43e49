"""CUDA kernels of the ray-analysis engine (``backend="cuda"``; needs ``numba.cuda``).

The walk itself is not written again: :func:`_numba_kernels._walk_ray` and the functions it
calls (the sample positions, the table index, the empty-space jumps, VTK's shading and the
walk behind early ray termination) are compiled a second time from the same Python, as CUDA
device functions (:func:`_device_twins`), so the two back ends cannot drift.  One thread
walks one ray (:func:`walk`, the same per-ray body as :func:`_numba_kernels.walk`) into flat
per-ray buffers; with a cache each ray packs its entries from the start of its own region
(``base``, an exclusive sum of its sample counts: a ray has at most one entry per sample),
and :func:`compact` then packs them in row-major pixel order, as the CPU engine stores them.
The per-volume arrays (table index, voxel records, cell and block maps, label map) and the
rays are made on the CPU by the numba kernels, so both back ends start from the same numbers.

Under ``NUMBA_ENABLE_CUDASIM=1`` numba's CUDA simulator runs these kernels in Python (every
thread, slowly): what the tests use without a GPU.
"""

from __future__ import annotations

import types

import numpy as np

from dvr_perception.rays._cuda import numpy_for_numba_cuda

numpy_for_numba_cuda()  # before numba.cuda is imported
from numba import cuda  # noqa: E402

from dvr_perception.rays import _numba_kernels as _nk  # noqa: E402

__all__ = ["BLOCK", "compact", "finish", "walk"]

#: Threads per block of :func:`walk`: (x, y) pixels, a tile of neighbouring rays.
BLOCK = (16, 8)
#: The device functions compiled from :mod:`_numba_kernels`' Python (callees first).
_SHARED = (
    "_jump_scale",
    "_sample_at",
    "_table_index",
    "_entry",
    "_block_exit",
    "_occupied",
    "_shade_at",
    "_tail",
    "_walk_ray",
)


def _device_twins() -> dict:
    """Return CUDA device functions of :data:`_SHARED`, compiled from the numba kernels' Python.

    Each function gets a copy of :mod:`_numba_kernels`' globals in which the names of the
    other shared functions are their device twins, so a device function calls device
    functions (resolved when the kernel is compiled).
    """
    glb = dict(vars(_nk))
    glb["_curv_at"] = cuda.jit(device=True)(_nk._dense_at)  # the GPU reads a dense |H|
    # its reshape, inlined in the IR: a device function cannot return a view it made
    glb["_flat"] = cuda.jit(device=True, inline="always")(_nk._flat)
    glb["_prefetch"] = cuda.jit(device=True, inline="always")(_nk._no_prefetch)  # CPU only
    twins = {}
    for name in _SHARED:
        py = getattr(_nk, name).py_func
        fn = types.FunctionType(py.__code__, glb, name, py.__defaults__, py.__closure__)
        fn.__doc__ = py.__doc__
        twins[name] = cuda.jit(device=True)(fn)
    glb.update(twins)
    return twins


_walk_ray = _device_twins()["_walk_ray"]


@cuda.jit
def walk(
    vol, tix, cells, blocks, occ, rep, lab, lab_base, kmap, tids, t_alpha, t_bit, smask, sdist, cap,
    curv, a, b, t_first, nsteps, base, step, ids, memb, alpha_r, alpha_w, col, light, tab, shade,
    has_curv, build, tail, ert, rgba, vis, asg, present, cimg, count, walked, aimp, state, c_lut,
    c_j, c_sh, c_curv, width, height,
):  # fmt: skip
    """One thread per ray: the per-ray body of :func:`_numba_kernels.walk`.

    A 2D grid over the image (``x`` column, ``y`` row); ray ``r = y * width + x`` packs its
    cache entries (with ``build``) from ``base[r]``.  Outputs as :func:`_numba_kernels.walk`.
    """
    x, y = cuda.grid(2)
    if x >= width or y >= height:
        return
    r = y * width + x
    tmaps = (kmap, tids, t_alpha, t_bit, smask, sdist, cap)
    maps = (tix, cells, blocks, occ, rep, lab, lab_base, tmaps)
    geo = (vol.shape[2], vol.shape[1], vol.shape[0], 0, 0, 0)
    count[r] = 0
    for s in range(vis.shape[0]):
        vis[s, r] = 0.0
    for s in range(asg.shape[0]):
        asg[s, r] = 0.0
    present[r] = 0
    if nsteps[r] == 0:
        rgba[r, 0] = 0.0
        rgba[r, 1] = 0.0
        rgba[r, 2] = 0.0
        rgba[r, 3] = 0.0
        cimg[r] = 0.0
        walked[r] = 0
        aimp[r] = 0.0
        return
    for q in range(7):
        state[r, q] = 1.0 if q == 3 or q == 4 else 0.0
    cnt, wk = _walk_ray(
        r, vol, maps, curv, a, b, t_first[r], (0, np.int64(nsteps[r])), step, ids, memb,
        alpha_r, alpha_w, col, light, tab, shade, has_curv, build, tail, base[r], ert, vis, asg,
        state, present, geo, (c_lut, c_j, c_sh, c_curv),
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


@cuda.jit
def finish(rgba, vis, cimg, asg, aimp, walked, bg, rgba32, image, acc, vis32, cimg32, asg32,
           aimp32, total):  # fmt: skip
    """float32 outputs and the image over the background, one thread per ray.

    The per-ray body of :func:`_numba_kernels.finish` (the same float32 operations), so only
    float32 buffers travel back to the host; also the assigned opacities (the first rows of
    ``asg``) and ``aimp`` in float32 (as the host's ``astype``), and the walked samples summed
    into ``total[0]`` (zeroed by the caller) instead of a per-ray array.
    """
    r = cuda.grid(1)
    if r >= rgba.shape[0]:
        return
    one = np.float32(1.0)
    zero = np.float32(0.0)
    a = np.float32(rgba[r, 3])
    for c in range(3):
        v = np.float32(rgba[r, c])
        rgba32[r, c] = v
        im = v + (one - a) * bg[c]
        image[r, c] = min(max(im, zero), one)
    rgba32[r, 3] = a
    acc[r] = a
    cimg32[r] = np.float32(cimg[r])
    for s in range(vis.shape[0]):
        vis32[s, r] = np.float32(vis[s, r])
    for s in range(asg32.shape[0]):
        asg32[s, r] = np.float32(asg[s, r])
    aimp32[r] = np.float32(aimp[r])
    w = walked[r]
    if w != 0:
        cuda.atomic.add(total, 0, w)


@cuda.jit
def compact(start, count, dest, src_lut, src_j, src_sh, src_curv, lut, j_, sh, curv, shade,
            has_curv):  # fmt: skip
    """Copy ray ``r``'s entries from ``start[r]`` to ``dest[r]`` (one thread per ray)."""
    r = cuda.grid(1)
    if r >= count.shape[0]:
        return
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
