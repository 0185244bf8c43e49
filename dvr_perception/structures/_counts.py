"""Histogram of an integer volume without a whole-volume index copy."""

from __future__ import annotations

import numpy as np

__all__ = ["int_histogram"]

#: Voxels per slab: ``np.bincount``'s int64 index copy is made for this many at a time.
SLAB = 1 << 22


def int_histogram(data: np.ndarray, lo: int, bins: int) -> np.ndarray:
    """Count the integer values ``lo .. lo + bins - 1`` in ``data``, in slabs.

    ``np.bincount`` needs an index array (8 bytes a voxel): made per slab of about 4 M
    voxels, never for the whole volume.

    Examples
    --------
    >>> int_histogram(np.array([[3, 4], [4, 6]], np.uint16), 3, 4).tolist()
    [1, 2, 0, 1]
    """
    counts = np.zeros(bins, np.int64)
    flat = data.reshape(-1)
    for i in range(0, flat.size, SLAB):
        part = flat[i : i + SLAB].astype(np.int64) - lo
        counts += np.bincount(part, minlength=bins)[:bins]
    return counts
