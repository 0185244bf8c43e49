"""Which structure each voxel belongs to: range structures by value, label structures by label.

:func:`classify_structures` is the public function; :func:`_classify` is the per-slice engine
that :mod:`dvr_perception.rays.curvature` streams (numba's ``classify_slice`` when given, a
lookup table for 8- and 16-bit unsigned data).
"""

from __future__ import annotations

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = ["classify_structures"]


def _classify(data: np.ndarray, labels, spec, nk=None, lut=None) -> np.ndarray:
    """Structure ids of ``data`` (any shape) and its ``labels`` (same shape, or None).

    ``lut`` (from :func:`_lookup_table`) gives the range structures' ids by value.
    """
    if lut is not None:
        ids = lut[data]
        for lab, k in _label_structures(spec):
            ids[labels == lab] = k
        return ids
    ids = np.full(data.shape, -1, dtype=np.int16)
    ranged = sorted((s.range[0], s.range[1], k) for k, s in enumerate(spec.structures) if s.range)
    touches = [
        n + 1 < len(ranged) and ranged[n + 1][0] <= hi for n, (_, hi, _) in enumerate(ranged)
    ]
    if ranged and nk is not None and data.ndim == 2:
        nk.classify_slice(
            data,
            np.array([r[0] for r in ranged], np.float64),
            np.array([r[1] for r in ranged], np.float64),
            np.array([not t for t in touches], np.bool_),
            np.array([r[2] for r in ranged], np.int16),
            ids,
        )
    else:
        _range_ids(data, spec, ids)
    for lab, k in _label_structures(spec):
        ids[labels == lab] = k
    return ids


def _range_ids(data: np.ndarray, spec, ids: np.ndarray) -> None:
    """Write the range structures' ids of ``data`` into ``ids`` (numpy)."""
    ranged = sorted((s.range[0], s.range[1], k) for k, s in enumerate(spec.structures) if s.range)
    for n, (lo, hi, k) in enumerate(ranged):
        touches_next = n + 1 < len(ranged) and ranged[n + 1][0] <= hi
        inside = data >= lo
        inside &= (data < hi) if touches_next else (data <= hi)
        ids[inside] = k


def _lookup_table(spec, dtype) -> np.ndarray | None:
    """Range-structure id of every value of an unsigned type of at most 16 bits, else None."""
    dtype = np.dtype(dtype)
    if dtype.kind != "u" or dtype.itemsize > 2:
        return None
    values = np.arange(2 ** (8 * dtype.itemsize), dtype=np.int64).astype(dtype)
    ids = np.full(values.shape, -1, dtype=np.int16)
    _range_ids(values, spec, ids)
    return ids


def _label_structures(spec) -> list[tuple[int, int]]:
    """``(label, structure index)`` of the label structures, in spec order."""
    return [(s.label, k) for k, s in enumerate(spec.structures) if s.label is not None]


def classify_structures(volume, spec) -> np.ndarray:
    """Structure id of every voxel (index into ``spec.structures``; ``-1`` for none).

    A range structure ``[lo, hi]`` owns the values ``lo <= v < hi``, and also ``v == hi`` when
    no other range starts there (touching ranges give the shared value to the upper structure).
    Label structures own the voxels whose label equals their id and take precedence.

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> from dvr_perception.structures import Structure, StructureSpec
    >>> vol = Volume(np.array([0, 10, 20, 30], np.uint8).reshape(1, 2, 2).repeat(2, 0))
    >>> s = lambda n, r: Structure(n, 0.5, (1, 1, 1), range=r)
    >>> spec = StructureSpec((s("a", (5, 20)), s("b", (20, 30))))
    >>> classify_structures(vol, spec)[0].tolist()
    [[-1, 0], [1, 1]]
    """
    _check_labels(volume, spec)
    return _classify(volume.data, volume.labels, spec)


def _check_labels(volume, spec) -> None:
    if _label_structures(spec) and volume.labels is None:
        raise DVRInputError(
            f"volume {volume.name!r}: the spec has label structures but the volume has "
            "no label volume"
        )
