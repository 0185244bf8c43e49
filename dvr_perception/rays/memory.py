"""How much memory an analysis needs, the limit it must stay under, and whether to brick.

:func:`plan` estimates, before anything large is allocated, what a whole-volume analysis
(:func:`~dvr_perception.rays.engine.analyze`'s usual path) and a bricked one
(:mod:`~dvr_perception.rays.bricks`) would hold at their peak: the derived volumes (table
index, voxel records with the normal codes, cell map, compact index, label map), the cache of
per-ray samples and the walk's scratch, and the per-ray buffers; the whole-volume estimate
also holds the volume itself and the whole ``|H|`` curvature volume it reads, so it is the
peak memory of the run (:func:`whole_volume_bytes`).  The whole volume is used whenever that
estimate fits the limit, however many voxels it has; otherwise bricks whose derived volumes
and scratch take a small share of the limit.  When even bricks do not fit,
:func:`plan` raises one error naming ``--memory-limit`` instead of letting the operating system
kill the process.

Both estimates count everything that stays alive while the analysis runs, not only what it
allocates: the volume itself, the memos the engine keeps between analyses of the volume (the
whole volume's derived volumes of :mod:`~dvr_perception.rays._grid`, the bricks' derived
volumes and curvature pieces of :mod:`~dvr_perception.rays.bricks`; :func:`kept_bytes`), the
bricked walk's reused buffers, and a whole-volume ``|H|`` array handed to a bricked analysis
(not the shading tables: a few MB whatever the volume).
A memo the chosen way does not read (the whole volume's derived volumes in a bricked run, the
bricks' memos and buffers in a whole one) is dropped unless it fits beside :data:`MARGIN`
times the run's estimate (analyses that alternate between the ways keep both while they fit
easily); the bricks' memo and
kept normal codes take at most :data:`~dvr_perception.rays.bricks.MEMO_SHARE` of what the
estimate leaves under the limit.  So the measured peak of an analysis, its memos included,
stays under the limit (``tests/rays/test_plan_kept.py`` measures it).

The limit (:mod:`dvr_perception._memory`, read by the volume readers too) is, in order: the
``memory_limit`` argument, :func:`set_limit` (the command line's
``--memory-limit``), the environment variable ``DVR_PERCEPTION_MEMORY_LIMIT`` and
:data:`DEFAULT_FRACTION` (a quarter) of the machine's physical memory; the rest is left to
Python and its libraries, VTK's renderer (its own copy of the volume) and the machine's other
programs.  Sizes here are binary (GB = 2**30 bytes).  The whole-volume estimate
(:func:`whole_volume_bytes`) counts the volume's own bytes, about 10 a voxel for the
derived volumes and ``|H|``, and 348 a pixel; a volume is analysed whole whenever that fits
the limit, else in bricks.
"""

from __future__ import annotations

import math
import threading
import weakref

import numpy as np

from dvr_perception._memory import (
    DEFAULT_FRACTION,
    ENV,
    human_bytes,
    limit,
    machine_memory,
    parse_size,
    set_limit,
)
from dvr_perception.errors import DVRInputError

__all__ = [
    "DEFAULT_FRACTION",
    "ENV",
    "Plan",
    "check_image",
    "drop_kept",
    "keeps",
    "kept_bytes",
    "limit",
    "machine_memory",
    "parse_size",
    "plan",
    "ray_bytes",
    "set_limit",
    "whole_fits",
    "whole_volume_bytes",
]

#: A brick's derived volumes and scratch may take this share of the limit.
BRICK_SHARE = 0.125
#: Bytes a voxel of the temporaries made beside the derived volumes while they are built
#: (the table index beside the voxel records being built from it; without numba, the block
#: map's empty-cell mask and its padded copy, :func:`~dvr_perception.rays._grid.block_map`).
TRANSIENT_VOXEL_BYTES = 2
#: Bytes a voxel of the temporaries of a brick's curvature piece computed from the volume
#: (:class:`~dvr_perception.rays.curvature_field.CurvatureField`: smoothed planes with their
#: margins; measured 32 inside a 128-voxel phantom).
CURVATURE_PIECE_BYTES = 32
#: The bricks' sample runs (16 bytes a ray and brick) are kept up to this many bytes
#: (:func:`dvr_perception.rays.bricks._runs`).
RUNS_BYTES = 256 * 2**20
# the limit itself (default, --memory-limit, environment) is read on the ground floor, where the
# volume readers use it too
_human = human_bytes


#: What the engine keeps between analyses: name -> (bytes kept for a volume, drop them).
_KEEPERS: dict = {}


def keeps(name: str, size, drop, *, per_volume: bool = True) -> None:
    """Register a memo the engine keeps between analyses, so :func:`plan` counts it.

    ``size(volume)`` returns the bytes the memo holds for ``volume`` (``per_volume`` False:
    for every volume, e.g. reused buffers) and ``drop(volume)`` frees them.
    """
    _KEEPERS[name] = (size, drop, per_volume)


def _nbytes(obj, seen) -> int:
    """Bytes of the arrays in ``obj`` (dicts, tuples and lists walked; each array once)."""
    if isinstance(obj, np.ndarray):
        base = obj
        while isinstance(base.base, np.ndarray):
            base = base.base
        if id(base) in seen:
            return 0
        seen.add(id(base))
        return int(base.nbytes)
    if isinstance(obj, dict):
        return sum(_nbytes(v, seen) for v in list(obj.values()))
    if isinstance(obj, tuple | list):
        return sum(_nbytes(v, seen) for v in obj)
    return 0


def array_bytes(*objs) -> int:
    """Bytes of the distinct arrays in ``objs`` (walking dicts, tuples and lists).

    Examples
    --------
    >>> a = np.zeros(100, np.uint8)
    >>> array_bytes({"a": a, "b": (a[:10], np.zeros(5))})  # a view of a counts once
    140
    """
    seen: set = set()
    return sum(_nbytes(o, seen) for o in objs)


def _grid_size(volume) -> int:
    from dvr_perception.rays import _grid

    try:
        memo = _grid._STORE.get(volume)
    except TypeError:  # not weak-referenceable: nothing memoised
        return 0
    return array_bytes(memo) if memo else 0


def _grid_drop(volume) -> None:
    from dvr_perception.rays import _grid

    try:
        memo = _grid._STORE.get(volume)
    except TypeError:
        return
    for key in [k for k in list(memo or ()) if k != "range"]:
        memo.pop(key, None)  # (another thread may have dropped it)


#: The whole volume's derived volumes (:mod:`~dvr_perception.rays._grid`, per volume).
keeps("whole", _grid_size, _grid_drop)


def _tables_size(_volume=None) -> int:
    from dvr_perception.rays import _tables

    return array_bytes(
        dict(_tables._SHADING_MEMO), dict(_tables._LIGHT_MEMO), list(_tables._DIRECTIONS)
    )


def _tables_drop(_volume=None) -> None:
    from dvr_perception.rays import _tables

    _tables._SHADING_MEMO.clear()
    _tables._LIGHT_MEMO.clear()


#: The shading tables and their light columns (a few MB whatever the volume: reported by
#: :func:`kept_bytes`, not counted by :func:`plan`).
keeps("tables", _tables_size, _tables_drop, per_volume=False)
#: A memo the chosen way does not read is kept only while this many times the run's
#: estimate fits beside it (the estimate is within 1.3x of the measured peak,
#: ``tests/rays/test_plan_kept.py``).
MARGIN = 1.5
#: The memos only a bricked analysis reads (:mod:`~dvr_perception.rays.bricks` keeps them).
BRICKED_MEMOS = ("bricks", "bricks_buffers", "bricks_runs")


def kept_bytes(volume, names=None) -> dict[str, int]:
    """Bytes the engine keeps between analyses, per memo (:func:`keeps`), for ``volume``.

    ``names``: only these memos.  A memo of another volume is not counted (it goes with its
    volume); buffers reused by every analysis are.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> from dvr_perception.rays import _grid
    >>> vol, _ = make_phantom(size=16)
    >>> kept_bytes(vol, ["whole"])
    {'whole': 0}
    >>> _ = _grid.index_volume(vol, 0.0, 1.0, 256)  # a derived volume, 2 bytes a voxel
    >>> kept_bytes(vol, ["whole"])
    {'whole': 8192}
    """
    out = {}
    for name, (size, _, per_volume) in list(_KEEPERS.items()):
        if names is None or name in names:
            out[name] = int(size(volume) if per_volume else size(None))
    return out


def drop_kept(volume, names) -> None:
    """Free the memos ``names`` (:func:`keeps`) of ``volume``."""
    for name in names:
        entry = _KEEPERS.get(name)
        if entry is not None:
            entry[1](volume)


def ray_bytes(k: int) -> int:
    """Bytes of the per-ray buffers of an analysis with ``k`` structures (one ray)."""
    return 8 * (4 + 1 + 2 * k + 1 + 8 + 7) + 4 * (9 + 2 * k)


def check_image(width: int, height: int, k: int = 1, *, source: str = "--size",
                memory_limit=None) -> None:  # fmt: skip
    """Refuse an image whose per-ray buffers alone exceed the memory limit.

    Checked as soon as the image size is known (``--size``, a camera file), before the volume
    is read.

    Examples
    --------
    >>> check_image(512, 512, memory_limit="1G") is None
    True
    """
    cap = limit(memory_limit)
    need = int(width) * int(height) * ray_bytes(max(int(k), 1))
    if need > cap:
        raise DVRInputError(
            f"{source}: an image of {width}x{height} pixels needs about {_human(need)} for its "
            f"per-pixel buffers alone, more than the memory limit of {_human(cap)}; use a "
            f"smaller image or raise --memory-limit (or {ENV})"
        )


def _voxel_bytes(volume, *, shade: bool, curvature: bool, compact: bool) -> int:
    """Bytes per voxel of the derived volumes a whole-volume analysis builds (and reads).

    The voxel records with the table index and the normal codes (4, shaded; else the table
    index, 2: :func:`~dvr_perception.rays._grid.index_in_records` keeps the index only inside
    the records), the compact index (1, tables of at most 256 entries), the cell map (1), the
    label map (1, with labels) and the float32 ``|H|`` volume (4, with curvature: its 8^3
    pages take at most that, and
    :func:`~dvr_perception.rays.curvature.curvature_pages` computes them holding only a
    few slices per thread besides, a band of slices per thread with label structures).
    The index's own 2 bytes while the records are built count as
    :data:`TRANSIENT_VOXEL_BYTES`.
    """
    n = (4 if shade else 2) + (1 if compact else 0) + 1
    n += 1 if getattr(volume, "labels", None) is not None else 0
    return n + (4 if curvature else 0)


def whole_volume_bytes(volume, *, shade: bool = True, curvature: bool = True,
                       compact: bool = True) -> int:  # fmt: skip
    """Bytes a whole-volume analysis holds in proportion to the volume.

    The volume itself and its derived volumes, with the blocks' occupancy bits (one bit a
    cell, :func:`~dvr_perception.rays._grid.block_occupancy`; :func:`plan` adds the per-ray
    buffers, the samples and the scratch).

    Examples
    --------
    >>> import numpy as np
    >>> vol = np.broadcast_to(np.uint16(0), (452, 512, 512))  # a CT's shape, no memory
    >>> round(whole_volume_bytes(type("V", (), {"data": vol})()) / 2**30, 2)  # 2 + 10 + 1/8 B
    1.34
    """
    data = volume.data
    per = _voxel_bytes(volume, shade=shade, curvature=curvature, compact=compact)
    return int(data.size) * (per + data.itemsize) + int(data.size) // 8


def _whole_share(volume, **kwargs) -> int:
    """:func:`whole_volume_bytes`, the label volume and the temporaries of the derived volumes."""
    labels = getattr(volume, "labels", None)
    extra = int(labels.nbytes) if labels is not None else 0
    return whole_volume_bytes(volume, **kwargs) + extra + TRANSIENT_VOXEL_BYTES * volume.data.size


def whole_fits(volume, memory_limit=None, **kwargs) -> bool:
    """Whether the volume's share of a whole-volume analysis fits the limit.

    :func:`whole_volume_bytes` (``kwargs``), with the label volume and the temporaries made
    while the derived volumes are built (:data:`TRANSIENT_VOXEL_BYTES`), against
    :func:`limit`: what :func:`~dvr_perception.rays.curvature_field.curvature_source` decides
    by (the ``|H|`` volume whole, or a field computed per brick), before the image size is
    known.
    """
    return _whole_share(volume, **kwargs) <= limit(memory_limit)


class Plan(dict):
    """What :func:`plan` decided.

    ``mode`` ("whole" or "bricks"), ``brick`` (cells, z y x), ``limit``, the estimated
    peak bytes of both ways (``whole``, ``bricked``; the memos kept included), ``held`` (the
    bytes every analysis of the volume holds: the volume, a whole ``|H|`` array, the kept
    whole-volume derived volumes), ``memo`` (the bricks' memo counted) and ``entries`` (the
    estimated cache entries).
    """


#: :func:`_filled_fraction` per volume and table (dropped with the volume).
_FILLED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_FILLED_LOCK = threading.Lock()


def _filled_fraction(volume, lut, memb, stride: int = 4) -> float:
    """Share of voxels whose table entry belongs to a structure (every ``stride``-th voxel).

    Remembered per volume object and table (a volume's data are not changed in place, as
    everywhere in the engine): a frame of a large volume spent tens of ms on it.
    """
    key = (float(lut.lo), float(lut.scale), int(lut.size), np.asarray(memb).tobytes(),
           id(volume.labels), int(stride))  # fmt: skip
    with _FILLED_LOCK:
        try:
            memo = _FILLED.setdefault(volume, {})
        except TypeError:  # not weak-referenceable: computed every time
            memo = {}
        hit = memo.get(key)
    if hit is None:
        hit = _filled_fraction_of(volume, lut, memb, stride)
        with _FILLED_LOCK:
            while len(memo) >= 4:
                memo.pop(next(iter(memo)))
            memo[key] = hit
    return hit


def _filled_fraction_of(volume, lut, memb, stride: int) -> float:
    inside = np.asarray(memb[: lut.size]) > 0
    d = volume.data[::stride, ::stride, ::stride].astype(np.float64)
    idx = np.clip(np.floor((d - lut.lo) * lut.scale), 0, lut.size - 1).astype(np.int64)
    frac = float(inside[idx].mean()) if idx.size else 1.0
    if volume.labels is not None:
        frac = max(frac, float(np.mean(volume.labels[::stride, ::stride, ::stride] > 0)))
    return frac


def plan(volume, nrays: int, samples: int, *, k: int, shade: bool, curvature: bool,
         build_cache: bool, lut, membership, memory_limit=None, brick=None,
         curvature_array: bool = False) -> Plan:  # fmt: skip
    """Choose whole or bricked and check the estimate against the limit.

    ``samples`` is the number of samples of all rays (the walk's segments), ``lut`` the
    transfer table and ``membership`` its per-entry membership.  ``brick`` forces bricks of
    that many cells.  ``curvature_array``: the curvature is a whole-volume array (alive
    beside a bricked run too), not a field computed per brick.  Raises
    :class:`~dvr_perception.errors.DVRInputError` when what the analysis itself allocates
    cannot fit even in bricks.

    Both estimates hold the volume and the memos kept for it (:func:`kept_bytes`); a memo
    the chosen way does not read is dropped (freed) when the run does not fit beside it.  The
    result's ``held`` is what every analysis of the volume holds (the volume, a whole
    ``|H|`` array, the kept whole-volume derived volumes) and ``memo`` the bricks' memo
    counted in ``bricked``.
    """
    cap = limit(memory_limit)
    voxels = int(volume.data.size)
    data = voxels * int(volume.data.itemsize)
    compact = lut.size <= 256
    per_voxel = _voxel_bytes(volume, shade=shade, curvature=False, compact=compact)
    entry = 2 + 4 + (4 if shade else 0) + (4 if curvature else 0)
    filled = _filled_fraction(volume, lut, membership) if build_cache else 0.0
    entries = samples * min(1.0, filled * 1.25 + 0.01)
    per_ray = ray_bytes(k)
    rays_bytes = nrays * per_ray
    cache = entries * entry if build_cache else 0.0
    scratch_whole = samples * entry if build_cache else 0.0
    kept = kept_bytes(volume)
    grid = kept.pop("whole", 0)  # the whole volume's derived volumes
    memo = kept.pop("bricks", 0)  # the bricks' derived volumes and curvature pieces
    runs = kept.pop("bricks_runs", 0)  # the bricks' sample runs of recent cameras
    kept.pop("tables", 0)  # a few MB whatever the volume: not counted (see the module)
    buffers = sum(kept.values())  # the bricked walk's reused buffers
    # the peak of the run: the volume, its derived volumes (those kept beyond them too) and
    # |H|, samples, scratch, rays
    labels = getattr(volume, "labels", None)
    labels = int(labels.nbytes) if labels is not None else 0
    whole_own = (
        _whole_share(volume, shade=shade, curvature=curvature, compact=compact)
        + max(grid - voxels * per_voxel, 0)  # those of other tables
        + scratch_whole
        + cache
        + rays_bytes
    )
    if brick is None:
        budget = BRICK_SHARE * cap
        edge = 256
        while edge > 32:
            bvox = (edge + 3) ** 3
            # the derived volumes only: the same bricks for every image size and cache
            # setting, so a volume's analyses share their memoised bricks
            if bvox * (per_voxel + volume.data.itemsize + 4) <= budget:
                break
            edge //= 2
        cells = tuple(min(edge, max(n - 1, 1)) for n in volume.data.shape)
    else:
        cells = tuple(int(c) for c in brick)
    bvox = math.prod(c + 3 for c in cells)
    held = data + labels
    held += 4 * voxels if curvature and curvature_array else 0
    nbricks = math.prod(
        -(-max(n - 1, 1) // c) for n, c in zip(volume.data.shape, cells, strict=True)
    )
    # a brick's derived volumes and their temporaries, its curvature piece (and the
    # temporaries of a piece computed from the volume)
    piece = per_voxel + TRANSIENT_VOXEL_BYTES + volume.data.itemsize
    piece += (4 + (0 if curvature_array else CURVATURE_PIECE_BYTES)) if curvature else 0

    def in_bricks(buffers, runs):
        # the walk's scratch and the bricks' entries go to reused buffers (grown, never
        # shrunk), the runs are kept for the next analyses
        walk = max(buffers, scratch_whole * min(1.0, bvox / max(voxels, 1)) * 2.0 + cache)
        return (
            held
            + bvox * piece
            + walk
            + min(runs + 16 * nrays * nbricks, RUNS_BYTES)
            + cache  # the bricks' entries merged
            + rays_bytes
        )

    bricked_own = in_bricks(buffers, runs)
    out = Plan(limit=cap, brick=cells, entries=entries)
    stale = max(grid - voxels * per_voxel, 0)  # derived volumes of other tables
    if brick is None and whole_own > cap >= whole_own - stale:
        drop_kept(volume, ["whole"])  # they alone kept the whole volume from fitting
        whole_own -= stale
        grid = 0
    if brick is None and whole_own <= cap:  # whole whenever it fits, however many voxels
        if MARGIN * whole_own + memo + buffers + runs > cap:  # the bricked walk's: not read
            drop_kept(volume, BRICKED_MEMOS)
            memo = buffers = runs = 0
        out.update(mode="whole", whole=whole_own + memo + buffers + runs,
                   bricked=bricked_own + grid + memo, held=held + grid, memo=memo)  # fmt: skip
        return out
    if bricked_own > cap >= in_bricks(0, 0):  # buffers of earlier runs, larger than this one's
        drop_kept(volume, ["bricks_buffers", "bricks_runs"])
        bricked_own = in_bricks(0, 0)
    if MARGIN * bricked_own + grid + memo > cap and grid:  # a bricked run does not read them
        drop_kept(volume, ["whole"])
        grid = 0
    if bricked_own + grid + memo > cap and memo:  # made again while they fit (bricks.py)
        drop_kept(volume, ["bricks"])
        memo = 0
    bricked = bricked_own + grid + memo
    out.update(whole=whole_own + memo + buffers + runs, bricked=bricked, held=held + grid,
               memo=memo)  # fmt: skip
    # refused when what the run itself allocates cannot fit (a brick's derived volumes, the
    # scratch, the bricks' entries and their merged copy, the per-ray buffers); what else it
    # counts (the volume, kept memos and buffers) bounds the memos and kept codes
    own = (
        bvox * (per_voxel + volume.data.itemsize)
        + scratch_whole * min(1.0, bvox / max(voxels, 1)) * 2.0
        + 2.0 * cache
        + rays_bytes
    )
    if own > cap:
        raise DVRInputError(
            f"memory: analysing volume {getattr(volume, 'name', '')!r} "
            f"({'x'.join(str(n) for n in volume.data.shape[::-1])} voxels) at {nrays} rays "
            f"needs about {_human(own)} even in bricks (of which {_human(2.0 * cache)} for the "
            f"cache of samples), more than the memory limit of {_human(cap)}; raise it with "
            f"--memory-limit (or {ENV}), or use a smaller image size"
        )
    out["mode"] = "bricks"
    return out
