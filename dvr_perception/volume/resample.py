"""Integer up-sampling of volumes: large test volumes made from the shared ones (issue 17).

The new voxel ``i`` along an axis with factor ``f`` sits at old index ``(i + 0.5) / f - 0.5``
(voxel centres of a grid ``f`` times finer covering the same cells), so the spacing becomes
``spacing / f`` and the origin moves by ``(1 / f - 1) * spacing / 2``.  Scalars are
interpolated trilinearly (clamped at the border, rounded back to integer types); labels take
the nearest old voxel.  The output is built one z slice at a time in float32, so no
full-size float64 (or float32) copy is ever made.
"""

from __future__ import annotations

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume.volume import Volume

__all__ = ["upsample"]


def _weights(n: int, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower and upper old index and the weight of the upper one, per new index."""
    s = np.clip((np.arange(n * f) + 0.5) / f - 0.5, 0, n - 1)
    i0 = np.floor(s).astype(np.intp)
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, (s - i0).astype(np.float32)


def upsample(volume: Volume, factors) -> Volume:
    """Return ``volume`` up-sampled by integer ``factors`` along x, y, z.

    Parameters
    ----------
    volume : Volume
        The volume (its label volume, if any, is up-sampled by nearest neighbour).
    factors : int or tuple of int
        Factor along x, y and z (each at least 1), or one factor for all three.

    Returns
    -------
    Volume
        ``dims`` are the old ones times the factors, same dtype.

    Examples
    --------
    >>> vol = Volume(np.arange(8, dtype=np.uint8).reshape(2, 2, 2), spacing=(1.0, 1.0, 2.0))
    >>> big = upsample(vol, (2, 1, 4))
    >>> big.dims, big.spacing
    ((4, 2, 8), (0.5, 1.0, 0.5))
    >>> big.data[0, 0].tolist()                     # x: 0 -> 0, 0.25, 0.75, 1
    [0, 0, 1, 1]
    """
    if isinstance(factors, (int, np.integer)):
        factors = (factors,) * 3
    try:
        fx, fy, fz = (int(f) for f in factors)
        ok = all(int(f) == f for f in factors)
    except (TypeError, ValueError):
        ok = False
    if not ok or min(fx, fy, fz) < 1:
        raise DVRInputError(
            f"upsample: factors must be three positive integers (x, y, z), got {factors!r}"
        )
    data = volume.data
    nz, ny, nx = data.shape
    z0, z1, wz = _weights(nz, fz)
    y0, y1, wy = _weights(ny, fy)
    x0, x1, wx = _weights(nx, fx)
    wy = wy[:, None]
    out = np.empty((nz * fz, ny * fy, nx * fx), data.dtype)
    integer = data.dtype.kind in "ui"
    info = np.iinfo(data.dtype) if integer else None
    for k in range(nz * fz):
        a = data[z0[k]].astype(np.float32)
        if wz[k] != 0:
            a += wz[k] * (data[z1[k]].astype(np.float32) - a)
        a = a[y0] + wy * (a[y1] - a[y0])
        a = a[:, x0] + wx * (a[:, x1] - a[:, x0])
        if integer:
            np.rint(a, out=a)
            np.clip(a, info.min, info.max, out=a)
        out[k] = a
    labels = None
    if volume.labels is not None:
        labels = volume.labels[np.arange(nz * fz) // fz][:, np.arange(ny * fy) // fy]
        labels = np.ascontiguousarray(labels[:, :, np.arange(nx * fx) // fx])
    f = (fx, fy, fz)
    spacing = tuple(s / k for s, k in zip(volume.spacing, f, strict=True))
    shift = [(1.0 / k - 1.0) * s / 2 for s, k in zip(volume.spacing, f, strict=True)]
    origin = tuple(np.asarray(volume.origin) + np.asarray(volume.direction) @ shift)
    return Volume(
        out,
        spacing=spacing,
        origin=origin,
        name=volume.name,
        source=volume.source,
        labels=labels,
        direction=volume.direction,
        oriented=volume.oriented,
    )
