"""Ray set-up and per-volume precomputation for the ray-analysis engine.

Everything here is plain numpy and is shared by the numba and the numpy back ends:

* :func:`clipping_range` - the near/far planes VTK's ``ResetCameraClippingRange`` would choose;
  the near plane anchors the sample phase (``docs/vtk_conventions.md`` facts 9-10).
* :func:`ray_segments` - per pixel ray: voxel-space origin and direction, position of the first
  sample and number of samples, exactly where ``vtkFixedPointVolumeRayCastMapper`` samples.
* :func:`index_volume`, :func:`compact_index`, :func:`normal_codes`, :func:`voxel_records`,
  :func:`cell_map` - per-volume arrays (table index per voxel, also as uint8 when it fits,
  VTK-encoded normals, both packed in one uint32 per voxel, class per cell; with
  :func:`block_map`, empty-space distance per block of cells), cached on the
  :class:`~dvr_perception.volume.volume.Volume` object for as long as it lives.
"""

from __future__ import annotations

import math
import mmap
import weakref

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "BLOCK",
    "CELL_EMPTY",
    "CELL_MIXED",
    "NO_CAP",
    "SATURATION",
    "ZERO_CODE",
    "block_map",
    "block_occupancy",
    "camera_pack",
    "cell_map",
    "clipping_range",
    "code_directions",
    "compact_index",
    "index_in_records",
    "index_source",
    "index_volume",
    "normal_codes",
    "ray_segments",
    "scalar_range",
    "skip_maps",
    "sparse_zeros",
    "structure_blocks",
    "structure_distances",
    "voxel_records",
]

#: VTK clips rays against the box of voxel centres moved in by this many voxels.
_INSET = 0.01
_STORE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


#: VTK's fixed-point trilinear weights sum to 32765/32768 and the index is rounded up.
_W_SCALE = 32765.0 / 32768.0
_W_BIAS = 32767.0 / 32768.0


def _fast():
    """Return the numba twins of the volume passes, or None (then numpy, slab by slab)."""
    from dvr_perception._numba import kernels

    return kernels("dvr_perception.rays._numba_grid")


def _store(volume) -> dict:
    """Per-volume memo (dropped together with the volume)."""
    d = _STORE.get(volume)
    if d is None:
        d = {}
        _STORE[volume] = d
    return d


#: Arrays of at least this many bytes are made by :func:`sparse_zeros` without huge pages.
SPARSE_BYTES = 8 * 2**20


def sparse_zeros(shape, dtype) -> np.ndarray:
    """``np.zeros(shape, dtype)`` whose memory is taken only where it is written.

    For large arrays that are written in part and read little: the cache-building walk's
    entries (each chunk of rays fills a region sized for all of its samples from its start,
    then they are copied out once).  Memory is taken page by page as it is written, but
    numpy asks for transparent huge pages (2 MiB) on large arrays, and every region touched
    then took whole huge pages (80-100 % of the walk's regions were resident instead of the
    entries' share).  An anonymous private mapping advised against huge pages keeps the
    resident part to the 4 KiB pages written; it is unmapped with the last view.  Not for
    arrays read at random (the ``|H|`` volume, 15 % of it never written, made the cache-
    building walk about 10 % slower without huge pages).  Small arrays, and systems without
    ``MADV_NOHUGEPAGE``: ``np.zeros``.

    Examples
    --------
    >>> a = sparse_zeros((3, 2**21), np.float32)
    >>> a.shape, a.dtype.name, bool(a.flags.writeable), float(a[2, 5])
    ((3, 2097152), 'float32', True, 0.0)
    """
    dt = np.dtype(dtype)
    count = int(np.prod(shape, dtype=np.int64))
    advice = getattr(mmap, "MADV_NOHUGEPAGE", None)
    if count * dt.itemsize < SPARSE_BYTES or advice is None or not hasattr(mmap, "MAP_PRIVATE"):
        return np.zeros(shape, dt)
    try:
        buf = mmap.mmap(-1, count * dt.itemsize, flags=mmap.MAP_PRIVATE)
        buf.madvise(advice)
    except (OSError, ValueError):  # no such advice here: ordinary memory
        return np.zeros(shape, dt)
    return np.frombuffer(buf, dt, count).reshape(shape)


def clipping_range(camera, bounds) -> tuple[float, float]:
    """Near/far distances VTK's ``ResetCameraClippingRange`` picks for ``bounds``.

    Uses ``ClippingRangeExpansion = 0.5`` and the 24-bit depth-buffer tolerance 0.001.

    Examples
    --------
    >>> from dvr_perception.rays.camera import Camera
    >>> cam = Camera(position=(5, 5, 50), focal_point=(5, 5, 5))
    >>> [round(v, 1) for v in clipping_range(cam, (0, 10, 0, 10, 0, 10))]
    [34.6, 58.2]
    """
    fwd, _, _ = camera.basis()
    b = np.asarray(bounds, float)
    corners = np.array([[x, y, z] for x in b[0:2] for y in b[2:4] for z in b[4:6]])
    dist = (corners - np.asarray(camera.position)) @ fwd
    near, far = float(dist.min()), float(dist.max())
    if camera.parallel_projection:
        min_gap = 0.2 * camera.parallel_scale
    else:
        min_gap = 0.2 * math.tan(math.radians(camera.view_angle) / 2.0) * far
    if far - near < min_gap:
        extra = min_gap - far + near
        far += extra / 2.0
        near -= extra / 2.0
    near = max(near, 0.0)
    near = 0.99 * near - (far - near) * 0.5
    far = 1.01 * far + (far - near) * 0.5
    if near >= far:
        near = 0.01 * far
    near = max(near, 0.001 * far)
    return near, far


def camera_pack(camera, volume, step: float) -> np.ndarray:
    """Camera, box and step packed into float64[29] for the numba ``segments`` kernel."""
    fwd, right, up = camera.basis()
    near, far = clipping_range(camera, volume.bounds)
    half = (
        camera.parallel_scale
        if camera.parallel_projection
        else math.tan(math.radians(camera.view_angle) / 2.0)
    )
    hi = np.asarray(volume.dims, float) - 1.0 - _INSET
    return np.concatenate(
        [
            camera.position, fwd, right, up,
            [half, float(camera.parallel_projection), camera.width, camera.height],
            volume.origin, volume.spacing, hi, [near, far, step, _INSET],
        ]
    ).astype(np.float64)  # fmt: skip


def ray_segments(camera, volume, step: float) -> dict:
    """Where every pixel's ray samples the volume (VTK's phase and clipping).

    Returns a dict of flat per-ray arrays (row-major pixels, row 0 at the top): ``a`` (R, 3)
    voxel-space ray origin, ``b`` (R, 3) voxel-space displacement per world unit, ``t`` (R,)
    world distance of the first sample, ``n`` (R,) int32 number of samples; sample ``j`` is at
    ``a + (t + j * step) * b``.
    """
    origins, dirs = camera.rays()
    fwd = camera.basis()[0]
    near, far = clipping_range(camera, volume.bounds)
    spacing = np.asarray(volume.spacing, float)
    a = ((origins - np.asarray(volume.origin, float)) / spacing).reshape(-1, 3)
    b = (dirs / spacing).reshape(-1, 3)
    cos = np.ones(len(a)) if camera.parallel_projection else dirs.reshape(-1, 3) @ fwd
    cos = np.maximum(cos, 1e-12)
    t_near, t_far = near / cos, far / cos
    lo = np.full(3, _INSET)
    hi = np.asarray(volume.dims, float) - 1.0 - _INSET
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - a) / b
        t2 = (hi - a) / b
    moving = b != 0
    t_lo = np.where(moving, np.minimum(t1, t2), -np.inf)
    t_hi = np.where(moving, np.maximum(t1, t2), np.inf)
    outside = (~moving & ((a < lo) | (a > hi))).any(axis=1)
    t_in = np.maximum(t_lo.max(axis=1), t_near)
    t_out = np.minimum(t_hi.min(axis=1), t_far)
    hit = (t_out > t_in) & ~outside
    length = np.where(hit, t_out - t_in, 0.0)
    t_in = t_in + 0.001 * length
    t_out = t_out - 0.001 * length
    with np.errstate(invalid="ignore"):
        k0 = np.floor((t_in - t_near) / step) + 1.0
        k1 = np.floor((t_out - t_near) / step)
    n = np.where(hit, np.maximum(k1 - k0 + 1.0, 0.0), 0.0).astype(np.int32)
    t_first = np.where(n > 0, t_near + k0 * step, 0.0)
    return {"a": np.ascontiguousarray(a), "b": np.ascontiguousarray(b), "t": t_first, "n": n}


def scalar_range(volume) -> tuple[float, float]:
    """``volume.scalar_range``, computed once per volume."""
    memo = _store(volume)
    if "range" not in memo:
        memo["range"] = volume.scalar_range
    return memo["range"]


def index_volume(volume, lo: float, scale: float, size: int) -> np.ndarray:
    """Per-voxel transfer-table index ``floor((v - lo) * scale)`` clipped, as uint16 [z, y, x]."""
    key = ("index", float(lo), float(scale), int(size))
    memo = _store(volume)
    if key not in memo:
        data = volume.data
        out = np.empty(data.shape, np.uint16)
        fast = _fast()
        if fast is not None:
            fast.index_volume(data, float(lo), float(scale), int(size), out)
        else:
            for z0 in range(0, data.shape[0], 16):
                v = (data[z0 : z0 + 16].astype(np.float64) - lo) * scale
                np.clip(np.floor(v), 0, size - 1, out=v)
                out[z0 : z0 + 16] = v
        memo[key] = out
    return memo[key]


def compact_index(volume, index: np.ndarray) -> np.ndarray:
    """``index`` as uint8 when every entry fits (memoised), else ``index`` itself.

    What the walk reads after early ray termination, where only the table index matters
    (the low 16 bits of each element): after :func:`index_in_records`, a table too large for
    uint8 is read from the voxel records.
    """
    key = ("index8", id(index))
    memo = _store(volume)
    if key not in memo:
        small = int(index.max(initial=0)) <= 255
        memo[key] = index.astype(np.uint8) if small else index_source(index)
    return memo[key]


def index_source(index: np.ndarray) -> np.ndarray:
    """Return the voxel records ``index`` is a view of (:func:`index_in_records`), else ``index``.

    What a walk that masks the low 16 bits reads for the table index: contiguous either way.
    """
    base = index.base
    if (isinstance(base, np.ndarray) and base.dtype == np.uint32 and base.shape == index.shape
            and not index.flags.c_contiguous):  # fmt: skip
        return base
    return index


def index_in_records(volume, index: np.ndarray, records: np.ndarray) -> np.ndarray:
    """Keep ``volume``'s table index only inside its voxel records from now on; return it.

    :func:`voxel_records` holds the table index in the low 16 bits of every record, so a
    whole-volume analysis with shading had the same numbers twice (2 of its 13 bytes per
    voxel: 226 MiB on a 512 x 512 x 452 CT).  The memoised ``index`` is replaced by a
    strided uint16 view of ``records`` (the same values, no memory of its own), and what was
    memoised for ``index`` (:func:`cell_map`, :func:`voxel_records`, :func:`compact_index`
    and :func:`structure_blocks`) is kept for the view, so ``index`` is freed as soon as the
    caller lets it go.  :func:`compact_index` then gives the uint8 index where the table
    fits it, else ``records`` (the walk masks the low 16 bits).  ``records`` must be
    ``voxel_records(volume, index, ...)``.
    """
    if index.base is records:  # already
        return index
    memo = _store(volume)
    if records.dtype != np.uint32 or records.shape != index.shape:
        raise ValueError("records: expected the uint32 voxel records of index")
    halves = records.view(np.uint16)  # (nz, ny, 2 nx): each record's two halves
    low = 0 if np.little_endian else 1
    view = halves[..., low::2]
    old, new = id(index), id(view)
    for key in [k for k in list(memo) if isinstance(k, tuple) and k and old in k[1:]]:
        value = memo.pop(key, None)
        if value is None:  # (another thread dropped it)
            continue
        if key[0] == "index8" and value is index:
            value = records  # the table does not fit uint8: the walk reads the records
        if key[0] == "sblocks":  # its index is compact_index's: now the records
            value = (weakref.ref(records), value[1])
            memo[("sblocks", id(records), *key[2:])] = value
            continue
        memo[tuple(new if v == old and i else v for i, v in enumerate(key))] = value
    for key, value in list(memo.items()):
        if value is index:
            memo[key] = view
    return view


#: Cell classes of :func:`cell_map`: no sample in the cell belongs to a structure, or its
#: samples need the trilinear table index; ``1 + s``: all are on structure ``s``'s plateau.
CELL_EMPTY = 0
CELL_MIXED = 255
#: Cell maps memoised per volume (the most recent tables).
_CELL_MAPS_KEPT = 3


def label_map(volume, label_ids) -> np.ndarray | None:
    """uint8 ``[z, y, x]``: ``1 + j`` where ``volume.labels`` equals ``label_ids[j]``, else 0.

    ``None`` when ``label_ids`` is empty.  A sample takes the label of its nearest voxel, and a
    voxel of a label structure belongs to it whatever its intensity (memoised per volume).
    """
    label_ids = tuple(int(v) for v in label_ids)
    if not label_ids:
        return None
    if volume.labels is None:
        raise DVRInputError(
            "volume.labels: the spec has label structures but the volume has no label volume "
            "(give the spec's 'labels' file, or Volume(..., labels=...))"
        )
    key = ("labelmap", label_ids)
    memo = _store(volume)
    if key not in memo:
        out = np.zeros(volume.labels.shape, np.uint8)
        for j, v in enumerate(label_ids):
            out[volume.labels == v] = 1 + j
        memo[key] = out
    return memo[key]


def cell_map(
    volume, index: np.ndarray, ids: np.ndarray, membership: np.ndarray, labels=None
) -> np.ndarray:
    """Class of every cell (uint8 ``[z, y, x]`` of its first corner; memoised).

    A sample's table index is interpolated from the cell's 8 corners, so it lies between their
    smallest and largest index (widened by one entry each way for VTK's fixed-point rounding
    and float error).  When every table entry in that interval is outside all structures the
    cell is :data:`CELL_EMPTY`; when every entry is on the plateau (membership 1) of one
    structure ``s`` it is ``1 + s`` (the sample's structure and opacity are then known without
    interpolating); otherwise :data:`CELL_MIXED`.  The last plane of each axis is never
    sampled (cells are clamped to ``n - 2``) and counts as empty.  ``labels``
    (:func:`label_map`): a cell with a labelled corner is mixed (its samples take their
    nearest voxel's label first).  Empty space is skipped by :func:`block_map`'s blocks; inside
    them the walk looks at every sample (cheaper than jumping over the short runs of noisy
    data).
    """
    ids = np.asarray(ids)
    memb = np.asarray(membership)
    key = (
        "cells", id(index), id(labels), ids.tobytes(), (memb > 0).tobytes(), (memb == 1).tobytes()
    )  # fmt: skip
    memo = _store(volume)
    if key in memo:
        return memo[key]
    n = len(ids)
    cat = np.where(memb <= 0, CELL_EMPTY, np.where(memb == 1, 1 + ids.astype(np.int64), CELL_MIXED))
    run = np.concatenate([[0], np.cumsum(cat[1:] != cat[:-1])])
    cat = cat.astype(np.uint8)
    nz = index.shape[0]
    fast = _fast()
    if fast is not None:
        out = np.empty(index.shape, np.uint8)
        has = labels is not None
        lab = labels if has else np.zeros((1, 1, 1), np.uint8)
        fast.cell_classes(index, cat, run.astype(np.int64), lab, has, out)
        nz = 0  # done: no slab below
    else:
        out = np.zeros(index.shape, np.uint8)
    for z0 in range(0, nz - 1, 16):
        z1 = min(z0 + 17, nz)
        blk = index[z0:z1]
        lo = np.minimum(blk[:-1], blk[1:])
        hi = np.maximum(blk[:-1], blk[1:])
        for axis in (1, 2):
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            a[axis] = slice(0, -1)
            b[axis] = slice(1, None)
            lo = np.minimum(lo[tuple(a)], lo[tuple(b)])
            hi = np.maximum(hi[tuple(a)], hi[tuple(b)])
        klo = np.floor(lo * _W_SCALE + _W_BIAS).astype(np.int64) - 2
        khi = np.floor(hi * _W_SCALE + _W_BIAS).astype(np.int64) + 1
        np.clip(klo, 0, n - 1, out=klo)
        np.clip(khi, 0, n - 1, out=khi)
        cls = np.where(run[klo] == run[khi], cat[klo], np.uint8(CELL_MIXED))
        if labels is not None:
            lab = labels[z0:z1] > 0
            lab = lab[:-1] | lab[1:]
            lab = lab[:, :-1] | lab[:, 1:]
            cls[lab[:, :, :-1] | lab[:, :, 1:]] = CELL_MIXED
        out[z0 : z0 + lo.shape[0], :-1, :-1] = cls
    # one map per transfer table: keep the newest few (editing ranges makes a new table each time)
    old = [k for k in list(memo) if isinstance(k, tuple) and k and k[0] == "cells"]
    for k in old[: max(len(old) - _CELL_MAPS_KEPT + 1, 0)]:
        memo.pop(k, None)  # (another thread may have dropped it)
    memo[key] = out
    return out


#: Side of the blocks of :func:`block_map`, in cells.
BLOCK = 4


def block_map(volume, cells: np.ndarray) -> np.ndarray:
    """Empty-space distance per block of ``BLOCK**3`` cells (uint8 ``[z, y, x]``; memoised).

    0 for a block with a cell that is not :data:`CELL_EMPTY` in ``cells`` (:func:`cell_map`);
    for an all-empty block, the chessboard distance ``d`` (in blocks, at most 255) to the
    nearest other block, so every block within ``d - 1`` blocks on each axis is empty too.
    Small enough to stay in the processor's cache where the cell map is not: the walk behind
    early ray termination reads it instead of the cell map.
    """
    key = ("blocks", id(cells))
    memo = _store(volume)
    hit = memo.get(key)
    if hit is not None and hit[0]() is cells:
        return hit[1]
    from scipy import ndimage

    fast = _fast()
    if fast is not None:  # (the numpy below: 4 s of a 1024 x 1024 x 904 CT's 22 s of maps)
        shape = tuple(-(-max(n - 1, 0) // BLOCK) for n in cells.shape)
        empty = np.empty(shape, np.bool_)
        fast.empty_blocks(cells, BLOCK, empty)
    else:
        c = cells[:-1, :-1, :-1] == CELL_EMPTY  # the last plane of each axis: no cells
        pad = [(0, -n % BLOCK) for n in c.shape]
        c = np.pad(c, pad, constant_values=True)
        bz, by, bx = (n // BLOCK for n in c.shape)
        empty = c.reshape(bz, BLOCK, by, BLOCK, bx, BLOCK).all(axis=(1, 3, 5))
    if empty.all():
        dist = np.full(empty.shape, 255, np.int64)
    else:
        dist = ndimage.distance_transform_cdt(empty, metric="chessboard")
    out = np.minimum(dist, 255).astype(np.uint8)
    old = [k for k in list(memo) if isinstance(k, tuple) and k and k[0] == "blocks"]
    for k in old[: max(len(old) - _CELL_MAPS_KEPT + 1, 0)]:
        memo.pop(k, None)  # (another thread may have dropped it)
    memo[key] = (weakref.ref(cells), out)
    return out


def block_occupancy(volume, cells: np.ndarray) -> np.ndarray:
    """Per block of :func:`block_map`, which of its ``BLOCK**3`` cells are not empty (memoised).

    uint64 ``[z, y, x]``: bit ``(z & 3) * 16 + (y & 3) * 4 + (x & 3)`` of the block holding
    cell ``(z, y, x)`` is set where ``cells`` is not :data:`CELL_EMPTY` (the last plane of
    each axis holds no cells: 0).  8 bytes per block, an eighth of the cell map's memory: the
    walk asks it whether a sample's cell is empty, and reads the cell map (which does not stay
    in the processor's cache) only for the others.  ``volume`` None: not memoised.
    """
    key = ("occupancy", id(cells))
    memo = _store(volume) if volume is not None else {}
    hit = memo.get(key)
    if hit is not None and hit[0]() is cells:
        return hit[1]
    shape = tuple(-(-max(n - 1, 0) // BLOCK) for n in cells.shape)
    fast = _fast()
    if fast is not None:
        out = np.empty(shape, np.uint64)
        fast.block_occupancy(cells, out)
    else:
        c = cells[:-1, :-1, :-1] != CELL_EMPTY
        c = np.pad(c, [(0, -n % BLOCK) for n in c.shape], constant_values=False)
        bz, by, bx = shape
        c = c.reshape(bz, BLOCK, by, BLOCK, bx, BLOCK).transpose(0, 2, 4, 1, 3, 5)
        bits = np.left_shift(np.uint64(1), np.arange(BLOCK**3, dtype=np.uint64))
        out = np.bitwise_or.reduce(np.where(c.reshape(bz, by, bx, -1), bits, np.uint64(0)),
                                   axis=-1).astype(np.uint64)  # fmt: skip
    old = [k for k in list(memo) if isinstance(k, tuple) and k and k[0] == "occupancy"]
    for k in old[: max(len(old) - _CELL_MAPS_KEPT + 1, 0)]:
        memo.pop(k, None)  # (another thread may have dropped it)
    memo[key] = (weakref.ref(cells), out)
    return out


#: Occlusion-free opacity at which a structure's presence on a ray has saturated (D8): the
#: walk behind early ray termination that skips (``analyze(..., exact=False)``) stops adding
#: to a structure's ``assigned`` there and stores ``min(assigned, SATURATION)``.  The presence
#: weight ``1 - exp(-a / 0.05)`` is then within 2.1e-9 of its exact value (1e-6 for a
#: ``presence_scale`` up to 0.072), and the transparency measure, which reads ``assigned``
#: capped at 0.7 (D7), reads the same numbers.
SATURATION = 1.0


def structure_blocks(volume, index: np.ndarray, entry_bits: np.ndarray, labels=None,
                     lab_base: int = -1) -> np.ndarray:  # fmt: skip
    """Bitmask of the structures each block of ``BLOCK**3`` cells can reach (uint32 ``[z, y, x]``).

    The blocks are :func:`block_map`'s.  A sample's table entry lies between the smallest and
    largest index of its cell's corners (widened as :func:`cell_map` widens it), so a block
    reaches the structures of the entries between the extremes of the voxels its cells touch
    (``4 b .. 4 b + 4`` on each axis), plus, with ``labels`` (:func:`label_map`, entry
    ``lab_base + v - 1`` for value ``v``), the label structures of those voxels.
    ``entry_bits``: per table entry the bit of its structure (0 outside every structure), at
    most 32 structures.  A superset is safe: the walk skips a block only when every structure
    in its mask has saturated on the ray.  Memoised per ``(index, labels, entry_bits)`` on
    ``volume`` (``None``: in a small module-level store).
    """
    bits = np.ascontiguousarray(entry_bits, np.uint32)
    key = ("sblocks", id(index), id(labels), bits.tobytes(), int(lab_base))
    memo = _store(volume) if volume is not None else _LOOSE
    hit = memo.get(key)
    if hit is not None and hit[0]() is index:
        return hit[1]
    n = len(bits)
    last = (lab_base if lab_base >= 0 else n) - 1  # the interpolated entry is at most this
    nz, ny, nx = index.shape
    shape = tuple(-(-(max(v - 1, 1)) // BLOCK) for v in (nz, ny, nx))
    # runs of entries with the same bits: a block ORs the runs between its extremes
    change = np.flatnonzero(bits[1:] != bits[:-1]) + 1
    run = np.zeros(n, np.int64)
    run[change] = 1
    run = np.cumsum(run)
    run_bits = bits[np.concatenate([[0], change])] if n else np.zeros(0, np.uint32)
    has = labels is not None
    lab = labels if has else np.zeros((1, 1, 1), np.uint8)
    fast = _fast()
    out = np.zeros(shape, np.uint32)
    if fast is not None:
        fast.structure_blocks(index, run, run_bits, bits, lab, has, int(lab_base), last, out)
    else:
        _structure_blocks_numpy(index, run, run_bits, bits, lab, has, int(lab_base), last, out)
    kept = _CELL_MAPS_KEPT if volume is not None else _LOOSE_KEPT
    old = [k for k in list(memo) if isinstance(k, tuple) and k and k[0] == "sblocks"]
    for k in old[: max(len(old) - kept + 1, 0)]:
        memo.pop(k, None)  # (another thread may have dropped it)
    memo[key] = (weakref.ref(index), out)
    return out


#: :func:`structure_blocks` of index volumes without their volume (a bricked walk's derived
#: volumes given without the piece): the newest few, checked by identity as above.
_LOOSE: dict = {}
_LOOSE_KEPT = 64


#: ``cap`` of the exact walk behind early ray termination (no structure ever saturates).
NO_CAP = 1e300


def skip_maps(volume, tix: np.ndarray, t_bit: np.ndarray, labels, lab_base: int, skip: bool,
              k: int):  # fmt: skip
    """``(smask, sdist, cap)``: the skipping walk behind early ray termination (``_tail``).

    ``skip``: :func:`structure_blocks` of ``tix`` (``t_bit``: per table entry its ``present``
    bit, a spare last entry ignored), their :func:`structure_distances` for the ``k``
    structures and :data:`SATURATION`; else placeholders and :data:`NO_CAP` (the exact walk).
    """
    if not skip:
        return np.zeros((1, 1, 1), np.uint32), np.zeros((1, 1, 1, 1), np.uint8), NO_CAP
    bits = np.asarray(t_bit)[: len(t_bit) - 1]
    smask = structure_blocks(volume, tix, bits, labels, lab_base)
    return smask, structure_distances(smask, k), SATURATION


#: :func:`structure_distances` are made only while they take at most this many bytes.
DISTANCES_BYTES = 128 * 2**20
_DIST: dict = {}
_DIST_KEPT = 64


def structure_distances(smask: np.ndarray, k: int) -> np.ndarray:
    """Per structure, each block's chessboard distance to the nearest block reaching it.

    uint8 ``(k, bz, by, bx)`` over :func:`structure_blocks`'s ``smask``: 0 for a block whose
    mask holds structure ``s``, else the distance ``d`` in blocks (at most 255; 255 where no
    block holds ``s``), so no block within ``d - 1`` blocks on each axis can reach ``s``.  A
    ray whose unsaturated structures are ``U`` may jump as far as :func:`block_map`'s empty
    space allows with ``min(d[s] for s in U)``.  Larger than :data:`DISTANCES_BYTES`: a
    ``(k, 1, 1, 1)`` array of zeros (no such jumps).  Memoised per ``smask`` (the newest few).
    """
    key = (id(smask), int(k))
    hit = _DIST.get(key)
    if hit is not None and hit[0]() is smask:
        return hit[1]
    if k * smask.size > DISTANCES_BYTES:
        return np.zeros((k, 1, 1, 1), np.uint8)
    from scipy import ndimage

    out = np.empty((k, *smask.shape), np.uint8)
    for s in range(k):
        far = (smask & np.uint32(1 << s)) == 0
        if far.all():
            out[s] = 255
        else:
            dist = ndimage.distance_transform_cdt(far, metric="chessboard")
            np.minimum(dist, 255, out=dist)
            out[s] = dist
    while len(_DIST) >= _DIST_KEPT:
        _DIST.pop(next(iter(_DIST)), None)
    _DIST[key] = (weakref.ref(smask), out)
    return out


def _structure_blocks_numpy(index, run, run_bits, bits, lab, has, lab_base, last, out):
    """:func:`structure_blocks` block by block in numpy (the numba twin's reference)."""
    b = BLOCK
    for zb, yb, xb in np.ndindex(out.shape):
        box = (slice(b * zb, b * zb + b + 1), slice(b * yb, b * yb + b + 1),
               slice(b * xb, b * xb + b + 1))  # fmt: skip
        v = index[box] & 0xFFFF  # the table index (also of voxel records)
        klo = min(max(math.floor(int(v.min()) * _W_SCALE + _W_BIAS) - 2, 0), last)
        khi = min(max(math.floor(int(v.max()) * _W_SCALE + _W_BIAS) + 1, 0), last)
        m = np.bitwise_or.reduce(run_bits[run[klo] : run[khi] + 1], initial=np.uint32(0))
        if has:
            lv = lab[box]
            lv = lv[lv > 0].astype(np.int64)
            m |= np.bitwise_or.reduce(bits[lab_base + lv - 1], initial=np.uint32(0))
        out[zb, yb, xb] = m


#: Code of a zero gradient in VTK's spherical direction encoding (``255 * 256``).
ZERO_CODE = 255 * 256
#: Radians to degrees, as the numba twin multiplies (``np.degrees`` may round otherwise).
_RAD2DEG = 180.0 / math.pi
#: ``floor(x)`` of an encoder position ``x`` within this of an integer is decided with libm.
_TIE = 1e-9


def _encoder_floor(pos: np.ndarray, exact) -> np.ndarray:
    """``floor(pos)``, with the positions next to an integer replaced by ``exact(near)`` first.

    numpy's vectorised ``arctan2``/``arcsin`` (SVML/SIMD, depending on the numpy version and
    the processor) differ from the C library's by an ulp or so, and the numba twin calls the C
    library.  A position on a rounding boundary (``phi = 45`` degrees is one: ``135 * 254 / 180
    + 0.5 = 191``) then falls on either side: 1 863 rgba values and E_s 1.3e-4 apart between
    ParaView's numpy 1.24 and numpy 2.4 on fuel.  ``exact(near)`` recomputes the positions
    within :data:`_TIE` of an integer with :mod:`math`, so the codes are the numba twin's under
    any numpy.
    """
    near = np.abs(pos - np.rint(pos)) < _TIE
    if near.any():
        pos[near] = exact(near)
    return np.floor(pos)


def _libm(func, *args: np.ndarray) -> np.ndarray:
    """``func`` of :mod:`math` (the C library) on each element of ``args``, as float64."""
    return np.array(list(map(func, *(a.tolist() for a in args))), np.float64)


def _theta_pos(theta: np.ndarray) -> np.ndarray:
    """Return ``theta * 255 / 359 + 0.5`` of azimuths in degrees (negative ones: + 360 first)."""
    theta[theta < 0] += 360.0
    return theta * (255.0 / 359.0) + 0.5


def _phi_pos(phi: np.ndarray) -> np.ndarray:
    """Return the encoder position ``(phi + 90) * 254 / 180 + 0.5`` of elevations in degrees."""
    return (phi + 90.0) * (254.0 / 180.0) + 0.5


def normal_codes(volume) -> np.ndarray:
    """Return encoded unit normals (negative gradient, central differences), uint16 ``[z, y, x]``.

    VTK's ``vtkSphericalDirectionEncoder`` (65536 codes, ``docs/vtk_conventions.md`` fact 19):
    ``lo = round(theta * 255 / 359)``, ``hi = round((phi + 90) * 254 / 180)``, code
    ``lo + 256 hi``; zero gradient -> :data:`ZERO_CODE`.  Border voxels use the voxel itself as
    the missing neighbour (``ComputeCS1CGradients``).  The angles near a rounding boundary come
    from the C library (:func:`_encoder_floor`): the same codes in every numpy.
    """
    memo = _store(volume)
    if "normal_codes" not in memo:
        data = volume.data
        spacing = np.asarray(volume.spacing, float)
        aspect = (2.0 * spacing / spacing.mean()).astype(np.float32)
        nz = data.shape[0]
        out = np.empty(data.shape, np.uint16)
        fast = _fast()
        if fast is not None:
            fast.normal_codes(data, aspect, out)
            nz = 0  # done: no slab below
        for z0 in range(0, nz, 16):
            z1 = min(z0 + 16, nz)
            lo, hi = max(z0 - 1, 0), min(z1 + 1, nz)
            v = np.pad(data[lo:hi].astype(np.float32), ((0, 0), (1, 1), (1, 1)), mode="edge")
            zpad = np.concatenate(
                [v[:1]] * (z0 == 0) + [v] + [v[-1:]] * (z1 == nz), axis=0
            )  # edge-replicate in z only at the volume border
            c = zpad[1:-1]
            gx = ((c[:, 1:-1, :-2] - c[:, 1:-1, 2:]) / aspect[0]).astype(np.float64)
            gy = ((c[:, :-2, 1:-1] - c[:, 2:, 1:-1]) / aspect[1]).astype(np.float64)
            gz = ((zpad[:-2, 1:-1, 1:-1] - zpad[2:, 1:-1, 1:-1]) / aspect[2]).astype(np.float64)
            mag = np.sqrt(gx * gx + gy * gy + gz * gz)
            zero = mag == 0
            mag[zero] = 1.0
            sin_phi = np.clip(gz / mag, -1.0, 1.0)
            lo_ = _encoder_floor(
                _theta_pos(np.arctan2(gy, gx) * _RAD2DEG),
                lambda m, gx=gx, gy=gy: _theta_pos(_libm(math.atan2, gy[m], gx[m]) * _RAD2DEG),
            )
            hi_ = _encoder_floor(
                _phi_pos(np.arcsin(sin_phi) * _RAD2DEG),
                lambda m, s=sin_phi: _phi_pos(_libm(math.asin, s[m]) * _RAD2DEG),
            )
            lo_, hi_ = np.clip(lo_, 0, 255), np.clip(hi_, 0, 254)
            code = (lo_ + 256.0 * hi_).astype(np.uint16)
            code[zero] = ZERO_CODE
            out[z0:z1] = code
        memo["normal_codes"] = out
    return memo["normal_codes"]


def code_directions() -> np.ndarray:
    """Return the decoded unit direction of every code (float64 (65536, 3); unused: zero)."""
    code = np.arange(65536)
    lo, hi = code % 256, code // 256
    phi = np.radians(-89.5 + hi * (179.0 / 254.0))
    theta = np.radians(lo * (359.0 / 255.0))
    d = np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)], axis=-1)
    d[hi == 255] = 0.0
    return d


def voxel_records(volume, index: np.ndarray, cells: np.ndarray | None = None) -> np.ndarray:
    """Per voxel ``index | code << 16`` (uint32 ``[z, y, x]``): one fetch per cell corner.

    With ``cells`` (:func:`cell_map`) and numba, codes are computed only at the corners of
    cells that are not empty, the only voxels shading reads (the others hold
    :data:`ZERO_CODE`); a few times faster on volumes with much empty space, and no separate
    code volume.  Memoised per ``(index, cells)`` (the newest two).
    """
    fast = _fast() if cells is not None else None
    key = ("records", id(index), id(cells) if fast is not None else None)
    memo = _store(volume)
    if key not in memo:
        out = np.empty(index.shape, np.uint32)
        if fast is not None:
            spacing = np.asarray(volume.spacing, float)
            aspect = (2.0 * spacing / spacing.mean()).astype(np.float32)
            fast.records_where(volume.data, aspect, index, cells, out)
        else:
            codes = normal_codes(volume)
            for z0 in range(0, index.shape[0], 16):
                out[z0 : z0 + 16] = codes[z0 : z0 + 16].astype(np.uint32) << np.uint32(16)
                out[z0 : z0 + 16] |= index[z0 : z0 + 16]
        old = [k for k in list(memo) if isinstance(k, tuple) and k and k[0] == "records"]
        for k in old[: max(len(old) - 1, 0)]:
            memo.pop(k, None)  # (another thread may have dropped it)
        memo[key] = out
    return memo[key]
