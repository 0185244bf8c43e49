"""The voxels of a generated, layered head-like phantom (its structure spec is in structures).

:func:`phantom_volume` generates the volume; the spec that goes with it, and
:func:`~dvr_perception.structures.phantom.make_phantom` (volume and spec together), are in
:mod:`dvr_perception.structures.phantom`, beside the other built-in data (the presets).

Geometry (``size = 128``; everything scales with ``size``): an ellipsoidal head (semi-axes
46, 56, 50 voxels along x, y, z) made of a **skin** shell, a **skull** shell and a filled
**brain**, and three inner objects in the brain: a **tumour** (sphere, behind the centre),
a **ventricle** (ellipsoid, in front of the centre) and a **calcification** (small sphere).
In the default view (camera on +z looking down -z, +y up) the image footprints show all four
layer relations: the skin *encloses* everything, ventricle and tumour *overlap* in projection
(but are 13 voxels apart in depth), tumour and calcification *touch* (footprints share pixel
edges but no pixel; different depths), ventricle and calcification are *separate*.

Intensities are ordered by spatial nesting (outer layers darker, inner objects brighter):
background 0 < skin 48 < skull 95 < brain 140 < tumour 180 < ventricle 214 < calcification
248, each in its own range with unclassified gaps in between.  A partial-volume transition
between two materials crosses only the values between them, so along the nesting path
(air -> skin -> skull -> brain -> tumour) no transition crosses a third structure.  The brain
has only one intensity neighbour above it, so the brain -> ventricle edge crosses the tumour
range and the brain -> calcification edge crosses tumour and ventricle: thin (sub-voxel)
halos; this is unavoidable when three objects of distinct ranges sit in one host and is why
the largest object (tumour) gets the clean rank.

The returned volume carries the ground-truth material map in ``Volume.labels``
(0 = background, ``i + 1`` = structure ``i`` of the spec), taken before blurring.
"""

from __future__ import annotations

import numbers

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume.volume import Volume

__all__ = ["PHANTOM_MATERIALS", "phantom_volume"]

#: name, intensity, structure range, importance, colour -- in label order (label = index + 1)
PHANTOM_MATERIALS: tuple[tuple[str, int, tuple[float, float], float, tuple], ...] = (
    ("skin", 48, (28.0, 70.0), 0.1, (0.95, 0.75, 0.6)),
    ("skull", 95, (72.0, 117.0), 0.15, (0.95, 0.95, 0.85)),
    ("brain", 140, (119.0, 161.0), 0.2, (0.85, 0.55, 0.65)),
    ("tumour", 180, (163.0, 197.0), 0.7, (1.0, 0.25, 0.15)),
    ("ventricle", 214, (199.0, 229.0), 0.8, (0.2, 0.5, 1.0)),
    ("calcification", 248, (231.0, 255.0), 0.9, (1.0, 0.9, 0.1)),
)

_HEAD = (46.0, 56.0, 50.0)  # semi-axes (x, y, z) of the skin's outer surface at size 128
_SHELLS = (1.0, 0.9, 0.8)  # skin outer, skull outer, brain outer, as fractions of _HEAD
# label, centre (x, y, z) relative to the volume centre, semi-axes (x, y, z); size-128 voxels
_OBJECTS = (
    (4, (8.0, 10.0, -14.0), (10.0, 10.0, 10.0)),  # tumour, behind
    (5, (-8.0, 10.0, 16.0), (12.0, 9.0, 7.0)),  # ventricle, in front, overlaps the tumour
    (6, (17.9, -3.2, 2.0), (6.0, 6.0, 6.0)),  # calcification, footprint edge-adjacent
)


def phantom_volume(*, size: int = 128, seed: int = 0, noise: float = 0.02) -> Volume:
    """Generate the layered head phantom's voxels.

    Parameters
    ----------
    size : int, optional
        Edge length in voxels (the volume is ``size**3``, spacing 1); 16 to 512.
    seed : int, optional
        Seed of the noise; the geometry does not depend on it.
    noise : float, optional
        Standard deviation of the additive Gaussian noise as a fraction of 255 (0 to 0.2).

    Returns
    -------
    Volume
        ``uint8`` volume named ``"phantom"`` with ground-truth ``labels`` (label ``i + 1`` is
        material ``i`` of :data:`PHANTOM_MATERIALS`).

    Examples
    --------
    >>> vol = phantom_volume(size=32)
    >>> vol.dims, vol.data.dtype, int(vol.labels.max())
    ((32, 32, 32), dtype('uint8'), 6)
    """
    size, seed, noise = _check(size, seed, noise)
    labels = _labels(size)
    values = np.array([0] + [m[1] for m in PHANTOM_MATERIALS], np.float32)
    data = values[labels]
    from scipy import ndimage  # imported here: importing the package takes 0.2-0.4 s

    ndimage.gaussian_filter(data, sigma=max(0.7, size / 128.0), output=data, truncate=3.0)
    if noise > 0:
        rng = np.random.default_rng(seed)
        data += rng.standard_normal(data.shape, dtype=np.float32) * np.float32(noise * 255.0)
    data = np.rint(np.clip(data, 0.0, 255.0)).astype(np.uint8)
    return Volume(data, name="phantom", source="phantom", labels=labels)


def _check(size, seed, noise) -> tuple[int, int, float]:
    if isinstance(size, bool) or not isinstance(size, numbers.Integral) or not 16 <= size <= 512:
        raise DVRInputError(f"make_phantom: size must be an integer in [16, 512], got {size!r}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise DVRInputError(f"make_phantom: seed must be a non-negative integer, got {seed!r}")
    try:
        noise_f = float(noise)
    except (TypeError, ValueError):
        noise_f = float("nan")
    if not 0.0 <= noise_f <= 0.2:
        raise DVRInputError(f"make_phantom: noise must be a number in [0, 0.2], got {noise!r}")
    return int(size), int(seed), noise_f


def _labels(size: int) -> np.ndarray:
    """Material map (uint8, ``[z, y, x]``) before blurring."""
    f = size / 128.0
    c = (size - 1) / 2.0
    ax = np.arange(size, dtype=np.float32) - np.float32(c)
    z, y, x = ax[:, None, None], ax[None, :, None], ax[None, None, :]
    hx, hy, hz = (h * f for h in _HEAD)
    q = (x / hx) ** 2 + (y / hy) ** 2 + (z / hz) ** 2  # 1 on the head surface
    labels = np.zeros((size, size, size), np.uint8)
    for label, frac in enumerate(_SHELLS, start=1):
        labels[q <= frac * frac] = label
    for label, centre, semi in _OBJECTS:
        (cx, cy, cz), (sx, sy, sz) = ((v * f for v in centre), (v * f for v in semi))
        inside = ((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2 + ((z - cz) / sz) ** 2 <= 1.0
        labels[inside] = label
    return labels


def __getattr__(name: str):
    # deprecated alias (one release): the phantom with its spec is in structures.phantom
    if name == "make_phantom":
        import warnings

        warnings.warn(
            "dvr_perception.volume.phantom.make_phantom is deprecated; use "
            "dvr_perception.structures.phantom.make_phantom (or dvr_perception.make_phantom)",
            DeprecationWarning,
            stacklevel=2,
        )
        from dvr_perception.structures.phantom import make_phantom  # layering: deprecated alias

        return make_phantom
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
