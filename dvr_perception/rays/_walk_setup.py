"""What the whole-volume walk and the bricked walk share (below both of them).

Input checks, the rays, the tables of the walk behind early ray termination, the order of
the rays, the rendering parameters and the finished
:class:`~dvr_perception.rays._results.RayAnalysis`: used by the whole-volume walk
(:mod:`~dvr_perception.rays.engine`) and the bricked one (:mod:`~dvr_perception.rays.bricks`).

Both walks import this module and neither imports the other at module level:
:func:`~dvr_perception.rays.engine.analyze` chooses between them (whole volume or bricks,
:func:`~dvr_perception.rays.memory.plan`) and imports the bricked one when it needs it.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from dvr_perception._numba import kernels
from dvr_perception.errors import DVRInputError
from dvr_perception.rays import _grid
from dvr_perception.rays._results import RayAnalysis, engine_made
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.spec import MAX_STRUCTURES, StructureSpec
from dvr_perception.volume.volume import Volume

BACKENDS = ("auto", "numba", "numpy", "cuda")
_MAX_STRUCTURES = MAX_STRUCTURES


def _numba_kernels():
    """Return the numba kernel module, or None when numba is unavailable or disabled."""
    return kernels("dvr_perception.rays._numba_kernels")


def _check_inputs(volume, spec, camera, backend) -> None:
    if not isinstance(volume, Volume):
        raise DVRInputError(f"volume: expected a Volume, got {type(volume).__name__}")
    if not isinstance(spec, StructureSpec):
        raise DVRInputError(f"spec: expected a StructureSpec, got {type(spec).__name__}")
    if not isinstance(camera, Camera):
        raise DVRInputError(f"camera: expected a Camera, got {type(camera).__name__}")
    k = len(spec.structures)
    if not 1 <= k <= _MAX_STRUCTURES:
        raise DVRInputError(f"spec.structures: expected 1 to {_MAX_STRUCTURES} structures, got {k}")
    if backend not in BACKENDS:
        raise DVRInputError(f"backend: expected one of {BACKENDS}, got {backend!r}")


def _check_curvature(curvature, volume):
    if curvature is None:
        return None
    from dvr_perception.rays.curvature_field import CurvatureField, CurvaturePages

    if isinstance(curvature, (CurvatureField, CurvaturePages)):
        if curvature.shape != volume.data.shape:
            raise DVRInputError(
                f"curvature: a field of shape {curvature.shape}, the volume is "
                f"{volume.data.shape} (z, y, x)"
            )
        if isinstance(curvature, CurvaturePages):
            return _checked_pages(curvature)
        return curvature  # computed piece by piece (bricks) or whole (below)
    try:
        c = np.asarray(curvature, dtype=np.float32)
    except (TypeError, ValueError):
        raise DVRInputError("curvature: expected a float array shaped like the volume") from None
    if c.shape != volume.data.shape:
        raise DVRInputError(
            f"curvature: expected shape {volume.data.shape} (z, y, x) like the volume, "
            f"got {c.shape}"
        )
    nk = _numba_kernels()
    if nk is not None:
        c = np.ascontiguousarray(c)
        state = _checked_curvature(nk, c)
        if state == 2:
            raise DVRInputError("curvature: values must be finite")
        return c if state == 0 else np.abs(c)  # already |H|: used as is, not copied
    if not np.all(np.isfinite(c)):
        raise DVRInputError("curvature: values must be finite")
    return np.ascontiguousarray(np.abs(c))


def _checked_pages(paged):
    """``paged`` with finite values checked (|values| when some are negative)."""
    nk = _numba_kernels()
    flat = paged.pages.reshape(-1)
    state = _checked_curvature(nk, paged.pages) if nk is not None else None
    if state is None:
        state = 2 if not np.all(np.isfinite(flat)) else int(bool((flat < 0).any()))
    if state == 2:
        raise DVRInputError("curvature: values must be finite")
    if state == 1:
        return type(paged)(paged.index, np.abs(paged.pages), paged.shape)
    return paged


#: A whole-volume walk's pages of a dense ``|H|`` array given by a caller, by array.
_PAGED: dict = {}
#: What the numba walk reads without curvature (the pages' types: one compiled variant).
_NO_PAGES = (np.full((1, 1, 1), -1, np.int32), np.zeros((0, 8, 8, 8), np.float32))


def walk_curvature(curv, kind: str):
    """Return the ``|H|`` argument of back end ``kind``'s walk kernels for checked ``curv``.

    numba reads pages (``(index, pages)``; a dense array is paged once and remembered while
    it lives), the NumPy and CUDA walks a dense array; without curvature a stand-in of the
    same type.
    """
    from dvr_perception.rays.curvature_field import CurvaturePages

    if kind != "numba":
        if curv is None:
            return np.zeros((2, 2, 2), np.float32)
        return np.asarray(curv, np.float32) if isinstance(curv, CurvaturePages) else curv
    if curv is None:
        return _NO_PAGES
    if isinstance(curv, CurvaturePages):
        return curv.kernel_arg()
    key = (id(curv), curv.ctypes.data, curv.shape)
    hit = _PAGED.get(key)
    if hit is not None and hit[0]() is curv:
        return hit[1].kernel_arg()
    paged = CurvaturePages.from_dense(curv)
    for k in [k for k, v in _PAGED.items() if v[0]() is None]:
        _PAGED.pop(k, None)
    _PAGED[key] = (weakref.ref(curv), paged)
    return paged.kernel_arg()


_CURV_CHECKED: dict = {}


def _checked_curvature(nk, c: np.ndarray) -> int:
    """``nk.check_curvature`` of ``c``, remembered for the same (live, read-only use) array.

    The same curvature array is passed frame after frame; a full pass over it costs several
    ms.  Like the cache, the engine assumes a curvature array is not modified in place.
    """
    key = (id(c), c.ctypes.data, c.shape)
    hit = _CURV_CHECKED.get(key)
    if hit is not None and hit[0]() is c:
        return hit[1]
    state = int(nk.check_curvature(c.reshape(-1)))
    for k in [k for k, v in _CURV_CHECKED.items() if v[0]() is None]:
        _CURV_CHECKED.pop(k, None)
    _CURV_CHECKED[key] = (weakref.ref(c), state)
    return state


def _segments(nk, camera, volume, step: float) -> dict:
    """Per-ray sample ranges (``_grid.ray_segments``; numba twin when available)."""
    if nk is None:
        return _grid.ray_segments(camera, volume, step)
    nrays = camera.width * camera.height
    seg = {
        "a": np.empty((nrays, 3)),
        "b": np.empty((nrays, 3)),
        "t": np.empty(nrays),
        "n": np.empty(nrays, np.int32),
    }
    nk.segments(_grid.camera_pack(camera, volume, step), seg["a"], seg["b"], seg["t"], seg["n"])
    return seg


def _segments_at(nk, camera, volume, step: float, rays: np.ndarray) -> dict:
    """:func:`_segments` of the flat pixel indices ``rays`` (numba): row ``i`` is ``rays[i]``.

    Each row equals the whole image's to the bit; a walk of a few rays sets up only them.
    """
    m = len(rays)
    seg = {"a": np.empty((m, 3)), "b": np.empty((m, 3)), "t": np.empty(m),
           "n": np.empty(m, np.int32)}  # fmt: skip
    nk.segments_at(_grid.camera_pack(camera, volume, step), np.ascontiguousarray(rays, np.int64),
                   seg["a"], seg["b"], seg["t"], seg["n"])  # fmt: skip
    return seg


def _finish(rgba, vis, asg, present, cimg, spec, camera, stats, cache, aimp) -> RayAnalysis:
    h, w = camera.height, camera.width
    k = len(spec.structures)
    bg = np.asarray(spec.background, np.float32)
    nk = _numba_kernels()
    if nk is not None and rgba.dtype == vis.dtype == cimg.dtype == np.float64:
        rgba32 = np.empty((h, w, 4), np.float32)
        image = np.empty((h, w, 3), np.float32)
        acc = np.empty((h, w), np.float32)
        vis32 = np.empty((k, h, w), np.float32)
        cimg32 = np.empty((h, w), np.float32)
        nk.finish(
            np.ascontiguousarray(rgba).reshape(-1, 4), np.ascontiguousarray(vis).reshape(k, -1),
            np.ascontiguousarray(cimg).reshape(-1), bg, rgba32.reshape(-1, 4),
            image.reshape(-1, 3), acc.reshape(-1), vis32.reshape(k, -1), cimg32.reshape(-1),
        )  # fmt: skip
        rgba, vis, cimg = rgba32, vis32, cimg32
    else:
        rgba = np.asarray(rgba, np.float32).reshape(h, w, 4)
        image = np.clip(rgba[..., :3] + (1.0 - rgba[..., 3:]) * bg, 0.0, 1.0)
        acc = np.ascontiguousarray(rgba[..., 3])
    return _analysis(rgba, image, acc, vis, asg, present, cimg, spec, camera, stats, cache, aimp)


def _analysis(rgba, image, acc, vis, asg, present, cimg, spec, camera, stats, cache, aimp):
    h, w = camera.height, camera.width
    k = len(spec.structures)
    analysis = RayAnalysis(
        rgba=rgba.reshape(h, w, 4),
        image=image.reshape(h, w, 3),
        accumulated=acc.reshape(h, w),
        visible=np.asarray(vis, np.float32).reshape(k, h, w),
        assigned=np.asarray(asg, np.float32).reshape(k, h, w),
        present=np.asarray(present, np.uint32).reshape(h, w),
        curvature=np.asarray(cimg, np.float32).reshape(h, w),
        names=spec.names,
        camera=camera,
        stats=stats,
        cache=cache,
        importance_accumulated=np.asarray(aimp, np.float32).reshape(h, w),
    )
    engine_made(analysis, mark=True)
    return analysis


#: The walk casts rays in tiles of this many pixels (rows, columns): neighbouring rays meet
#: the same voxels, so they stay in the processor's cache.
TILE = (16, 16)
#: Tiles are dealt to this many chunks (parallel work items, balanced load).
_CHUNKS = 64
#: With more threads than this, tile ``i`` goes to chunk ``floor(frac(i * _GOLDEN) *
#: chunks)`` (the golden ratio's fractional part: a low-discrepancy sequence), else to chunk
#: ``i % chunks`` (:func:`ray_order`).
_GOLDEN = (5.0**0.5 - 1.0) / 2.0
_SPREAD_THREADS = 4
_ORDERS: dict = {}
_ORDERS_LOCK = threading.Lock()


def ray_order(height: int, width: int, *, tile=TILE) -> tuple[np.ndarray, np.ndarray]:
    """Return the order in which the numba kernels visit the rays (memoised, read-only).

    Tiles of ``tile = (rows, columns)`` pixels, row by row inside a tile, are dealt to at
    most 64 chunks; chunk ``c`` visits ``order[chunk_ptr[c]:chunk_ptr[c + 1]]`` (flat pixel
    indices, every pixel exactly once).  The walk uses square tiles (:data:`TILE`);
    compositing from the cache uses whole image rows (``tile=(1, width)``), the order in
    which the cache entries are stored.

    With more than :data:`_SPREAD_THREADS` numba threads, tile ``i`` (row-major) goes to
    chunk ``floor(frac(i g) n)`` with ``g`` the golden ratio's fractional part: every chunk,
    and every run of consecutive chunks (what one thread gets from numba's static schedule
    of a parallel loop), takes tiles spread evenly over the image, so the threads get equal
    work however many there are.  Dealt round-robin (the default on fewer threads: its
    chunks sweep down tile columns, 3-4 % less work for the walk than spread tiles), a
    512-pixel image's 32 tile columns make each of the 64 chunks one column, and runs of
    adjacent columns go to one thread: 8 threads got no more done than 4 on the 512 x 512 x
    452 CT (issue 31; ``benchmarks/thread_balance.py``).  The order does not change any
    result: every ray is computed on its own.

    Examples
    --------
    >>> order, ptr = ray_order(3, 20)
    >>> len(ptr) - 1, sorted(order.tolist()) == list(range(60))
    (2, True)
    >>> order[: ptr[1]].tolist()[:18]
    [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 20, 21]
    >>> ray_order(3, 20, tile=(1, 20))[0][:4].tolist()
    [0, 1, 2, 3]
    """
    th, tw = (max(int(v), 1) for v in tile)
    spread = _threads() > _SPREAD_THREADS
    key = (int(height), int(width), th, tw, spread)
    with _ORDERS_LOCK:
        hit = _ORDERS.get(key)
    if hit is not None:
        return hit
    rows = np.arange(height * width, dtype=np.int64).reshape(height, width)
    ty, tx = -(-height // th), -(-width // tw)
    tiles = [rows[y * th : (y + 1) * th, x * tw : (x + 1) * tw].ravel()
             for y in range(ty) for x in range(tx)]  # fmt: skip
    nchunk = max(min(len(tiles), _CHUNKS), 1)
    deal = np.arange(len(tiles)) % nchunk
    if spread:
        deal = np.floor(np.mod(np.arange(len(tiles)) * _GOLDEN, 1.0) * nchunk).astype(np.int64)
    parts = [np.concatenate([tiles[i] for i in np.flatnonzero(deal == c)])
             for c in range(nchunk) if np.any(deal == c)]  # fmt: skip
    order = np.ascontiguousarray(np.concatenate(parts))
    chunk_ptr = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    order.flags.writeable = False
    chunk_ptr.flags.writeable = False
    with _ORDERS_LOCK:  # analyses may run in several threads (web app)
        while len(_ORDERS) >= 8:
            del _ORDERS[next(iter(_ORDERS))]
        _ORDERS[key] = (order, chunk_ptr)
    return order, chunk_ptr


def _threads() -> int:
    """Return numba's thread count (how many chunks run at once)."""
    import numba

    return max(1, int(numba.get_num_threads()))


def _group() -> int:
    """Chunks per kernel call when a progress callback is reported between calls."""
    return max(16, 4 * _threads())


def _interleaved(order, chunk_ptr, per: int):
    """Reorder the chunks so that every ``per`` consecutive ones are spread over the image.

    A kernel call over ``per`` consecutive chunks of :func:`ray_order` would take tiles from
    one stretch of its dealing sequence only, so its threads could get unequal shares of a
    region (a brick's footprint).  Here run ``g`` takes chunks ``g, g + G, g + 2G, ...``
    (``G`` runs), as the threads of one call over all the chunks do.  Every ray is still
    visited once.
    """
    nchunk = len(chunk_ptr) - 1
    runs = -(-nchunk // per)
    perm = [c for g in range(runs) for c in range(g, nchunk, runs)]
    parts = [order[chunk_ptr[c] : chunk_ptr[c + 1]] for c in perm]
    ptr = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    return np.ascontiguousarray(np.concatenate(parts)), ptr


def _tail_tables(ids, memb, alpha_w, rep, k):
    """Return what the walk behind early ray termination looks up (``_numba_kernels._tail``).

    ``kmap``: a cell class's table entry (a plateau's entry; the spare entry ``len(ids)``
    for empty and mixed cells); per table entry plus the spare, its structure (``k``, the
    spare row of ``asg``, outside every structure), its importance opacity (0 there) and its
    ``present`` bit (0 there).
    """
    n = len(ids)
    inside = memb > 0
    tids = np.append(np.where(inside, ids, k), k).astype(np.int64)
    t_alpha = np.append(np.where(inside, alpha_w, 0.0), 0.0)
    t_bit = np.where(tids < k, np.left_shift(1, np.minimum(tids, 31)), 0).astype(np.uint32)
    kmap = np.full(256, n, np.int64)
    for s in range(k):
        if rep[s] >= 0:
            kmap[1 + s] = rep[s]
    return kmap, tids, t_alpha, t_bit


def _with_labels(volume, spec, lut):
    """Return the label map and the table extended by one entry per label structure.

    Entry ``lut.size + j`` is label structure ``j`` (membership 1); a sample whose nearest
    voxel carries that label takes it, whatever its intensity.  Without label structures the
    map is ``None`` and the table is the intensity table.
    """
    lab_s = [i for i, s in enumerate(spec.structures) if s.label is not None]
    labmap = _grid.label_map(volume, [spec.structures[i].label for i in lab_s])
    ids = np.concatenate([lut.ids, np.asarray(lab_s, lut.ids.dtype)])
    memb = np.concatenate([lut.membership, np.ones(len(lab_s), lut.membership.dtype)])
    return labmap, np.ascontiguousarray(ids), np.ascontiguousarray(memb)


def _plateau_entries(ids, memb, k) -> np.ndarray:
    """Per structure, a table entry on its plateau (membership 1), or -1 (``_grid.cell_map``)."""
    rep = np.full(max(k, 1), -1, np.int64)
    for e in np.flatnonzero(memb == 1)[::-1]:
        rep[ids[e]] = e
    return rep


def _params(ops, cols, mats, direction) -> dict:
    """Return an analysis's rendering parameters as :func:`reevaluate` takes them (``stats``)."""
    return {
        "opacities": tuple(float(o) for o in ops),
        "colours": tuple(tuple(float(c) for c in row) for row in np.asarray(cols)),
        "lighting": tuple(mats),
        "light_direction": tuple(float(d) for d in np.asarray(direction, np.float64).ravel()),
    }
