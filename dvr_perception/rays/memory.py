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

The limit (:mod:`dvr_perception._memory`, read by the volume readers too) is, in order: the
``memory_limit`` argument, :func:`set_limit` (the command line's
``--memory-limit``), the environment variable ``DVR_PERCEPTION_MEMORY_LIMIT`` and
:data:`DEFAULT_FRACTION` of the machine's physical memory.  Sizes here are binary (GB =
2**30 bytes).  The whole-volume estimate (:func:`whole_volume_bytes`) counts the volume's own
bytes, about 11 a voxel for the derived volumes and ``|H|``, and 348 a pixel; a volume is
analysed whole whenever that fits the limit, else in bricks.
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
# the limit itself (default, --memory-limit, environment) is read on the ground floor, where the
# volume readers use it too
_human = human_bytes


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

    The table index (2), the voxel records with their normal codes (4, shaded), the compact
    index (1, tables of at most 256 entries), the cell map (1), the label map (1, with
    labels) and the float32 ``|H|`` volume (4, with curvature).
    """
    n = 2 + (4 if shade else 0) + (1 if compact else 0) + 1
    n += 1 if getattr(volume, "labels", None) is not None else 0
    return n + (4 if curvature else 0)


def whole_volume_bytes(volume, *, shade: bool = True, curvature: bool = True,
                       compact: bool = True) -> int:  # fmt: skip
    """Bytes a whole-volume analysis holds in proportion to the volume.

    The volume itself and its derived volumes (:func:`plan` adds the per-ray buffers, the
    samples and the scratch).

    Examples
    --------
    >>> import numpy as np
    >>> vol = np.broadcast_to(np.uint16(0), (452, 512, 512))  # a CT's shape, no memory
    >>> round(whole_volume_bytes(type("V", (), {"data": vol})()) / 2**30, 2)  # 2 + 11 B
    1.54
    """
    data = volume.data
    per = _voxel_bytes(volume, shade=shade, curvature=curvature, compact=compact)
    return int(data.size) * (per + data.itemsize)


def whole_fits(volume, memory_limit=None, **kwargs) -> bool:
    """Whether the volume's share of a whole-volume analysis fits the limit.

    :func:`whole_volume_bytes` (``kwargs``) against :func:`limit`: what
    :func:`~dvr_perception.rays.curvature_field.curvature_source` decides by (the ``|H|``
    volume whole, or a field computed per brick), before the image size is known.
    """
    return whole_volume_bytes(volume, **kwargs) <= limit(memory_limit)


class Plan(dict):
    """What :func:`plan` decided.

    ``mode`` ("whole" or "bricks"), ``brick`` (cells, z y x), ``limit`` and the estimated
    peak bytes of both ways (``whole``, ``bricked``).
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
         build_cache: bool, lut, membership, memory_limit=None, brick=None) -> Plan:  # fmt: skip
    """Choose whole or bricked and check the estimate against the limit.

    ``samples`` is the number of samples of all rays (the walk's segments), ``lut`` the
    transfer table and ``membership`` its per-entry membership.  ``brick`` forces bricks of
    that many cells.  Raises :class:`~dvr_perception.errors.DVRInputError` when the analysis
    cannot fit.
    """
    cap = limit(memory_limit)
    voxels = int(volume.data.size)
    compact = lut.size <= 256
    per_voxel = _voxel_bytes(volume, shade=shade, curvature=False, compact=compact)
    entry = 2 + 4 + (4 if shade else 0) + (4 if curvature else 0)
    filled = _filled_fraction(volume, lut, membership) if build_cache else 0.0
    entries = samples * min(1.0, filled * 1.25 + 0.01)
    per_ray = ray_bytes(k)
    rays_bytes = nrays * per_ray
    cache = entries * entry if build_cache else 0.0
    scratch_whole = samples * entry if build_cache else 0.0
    # the peak of the run: the volume, its derived volumes and |H|, samples, scratch, rays
    whole = (
        whole_volume_bytes(volume, shade=shade, curvature=curvature, compact=compact)
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
    bricked = (
        bvox * (per_voxel + volume.data.itemsize)
        + scratch_whole * min(1.0, bvox / max(voxels, 1)) * 2.0
        + 2.0 * cache  # the bricks' entries and their merged copy
        + rays_bytes
    )
    out = Plan(limit=cap, whole=whole, bricked=bricked, brick=cells, entries=entries)
    if brick is None and whole <= cap:  # whole whenever it fits, however many voxels
        out["mode"] = "whole"
        return out
    if bricked > cap:
        raise DVRInputError(
            f"memory: analysing volume {getattr(volume, 'name', '')!r} "
            f"({'x'.join(str(n) for n in volume.data.shape[::-1])} voxels) at {nrays} rays "
            f"needs about {_human(bricked)} even in bricks (of which {_human(2.0 * cache)} for the "
            f"cache of samples), more than the memory limit of {_human(cap)}; raise it with "
            f"--memory-limit (or {ENV}), or use a smaller image size"
        )
    out["mode"] = "bricks"
    return out
