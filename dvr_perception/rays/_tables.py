"""Parameter checking and per-render tables of the ray-analysis engine.

Turns user-facing overrides (opacities, colours, lighting, light direction, background) into the
arrays the kernels use, validating each one with a single :class:`DVRInputError` that names the
parameter.  Tables mimic VTK's fixed-point storage (``docs/vtk_conventions.md`` facts 4-5):
opacities are step-corrected only above 1e-4 and, like colours, rounded to 1/32767.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures.spec import Lighting

__all__ = [
    "ERT",
    "alpha_table",
    "check_opacities",
    "light_array",
    "material",
    "min_step",
    "shading_key",
    "shading_table",
    "stale_structures",
    "step_and_unit",
]

#: Smallest sample distance, as a share of the smallest voxel spacing: a smaller
#: ``rendering.sample_distance`` is clamped to it (with one warning), so a spec cannot ask for
#: an unbounded number of samples per ray.
MIN_STEP_FRACTION = 1.0 / 8.0
_WARNED: set = set()

#: VTK stops a ray once the remaining transmittance drops below 255/32767.
ERT = 255.0 / 32767.0
_FP = 32767.0


def _quantise(x: np.ndarray) -> np.ndarray:
    return np.floor(np.asarray(x, np.float64) * _FP + 0.5) / _FP


def check_opacities(opacities, k: int, name: str = "opacities") -> np.ndarray:
    """Validate ``k`` opacities in [0, 1]."""
    try:
        ops = np.asarray(opacities, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(f"{name}: expected {k} numbers in [0, 1], got {opacities!r}") from None
    if ops.ndim != 1 or ops.shape[0] != k:
        raise DVRInputError(
            f"{name}: expected {k} values (one per structure), got shape {ops.shape}"
        )
    if not np.all(np.isfinite(ops)) or np.any((ops < 0) | (ops > 1)):
        raise DVRInputError(f"{name}: every value must be in [0, 1], got {ops.tolist()}")
    return ops


def step_and_unit(spec, volume) -> tuple[float, float]:
    """Sample distance and opacity unit distance (defaults: smallest voxel spacing)."""
    rs = spec.rendering
    out = []
    for name, val in (
        ("sample_distance", rs.sample_distance),
        ("opacity_unit_distance", rs.opacity_unit_distance),
    ):
        v = float(min(volume.spacing)) if val is None else float(val)
        if not (math.isfinite(v) and v > 0):
            raise DVRInputError(f"rendering.{name}: must be a positive number, got {val}")
        out.append(v)
    return min_step(out[0], volume), out[1]


def min_step(step: float, volume) -> float:
    """Return ``step`` clamped to :data:`MIN_STEP_FRACTION` of the smallest voxel spacing.

    A clamped step is reported once per (step, spacing) as a :class:`DVRWarning`.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> import warnings
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")
    ...     min_step(1e-9, SimpleNamespace(spacing=(1.0, 2.0, 2.0)))
    0.125
    """
    floor = MIN_STEP_FRACTION * float(min(volume.spacing))
    if step >= floor:
        return step
    key = (step, floor)
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"rendering.sample_distance {step:g} is below {MIN_STEP_FRACTION:g} of the smallest "
            f"voxel spacing; using {floor:g}",
            DVRWarning,
            stacklevel=3,
        )
    return floor


def entry_opacity(ids: np.ndarray, memb: np.ndarray, ops: np.ndarray) -> np.ndarray:
    """Opacity of every table entry before the step correction: ``ops[s] * membership``."""
    return np.where(ids >= 0, ops[np.maximum(ids, 0)] * memb, 0.0)


def alpha_table(ids: np.ndarray, memb: np.ndarray, ops: np.ndarray, ratio: float) -> np.ndarray:
    """Step-corrected, 15-bit-rounded opacity of every table entry (float64[N])."""
    o = entry_opacity(ids, memb, ops)
    corr = np.where(o > 1e-4, 1.0 - np.power(np.clip(1.0 - o, 0.0, 1.0), ratio), o)
    return _quantise(corr)


def material(spec, *, colours=None, lighting=None) -> tuple[np.ndarray, tuple]:
    """Colours (K, 3) rounded like VTK's table, and the K :class:`Lighting` materials."""
    k = len(spec.structures)
    cols = np.array([s.colour for s in spec.structures], float) if colours is None else colours
    try:
        cols = np.asarray(cols, dtype=np.float64)
    except (TypeError, ValueError):
        raise DVRInputError(
            f"colours: expected {k} RGB triples in [0, 1], got {colours!r}"
        ) from None
    if cols.shape != (k, 3) or not np.all(np.isfinite(cols)) or cols.min() < 0 or cols.max() > 1:
        raise DVRInputError(
            f"colours: expected shape ({k}, 3) with values in [0, 1], got shape {cols.shape}"
        )
    mats = tuple(s.lighting for s in spec.structures) if lighting is None else tuple(lighting)
    if len(mats) != k or not all(isinstance(m, Lighting) for m in mats):
        raise DVRInputError(f"lighting: expected a sequence of {k} Lighting objects")
    for m in mats:
        vals = (m.ambient, m.diffuse, m.specular, m.specular_power)
        if not all(math.isfinite(float(v)) and float(v) >= 0 for v in vals):
            raise DVRInputError(f"lighting: coefficients must be finite and >= 0, got {m}")
    return _quantise(cols), mats


def light_array(camera, mats, direction, intensity: float) -> np.ndarray:
    """Pack materials and light geometry for the kernels: float64 (7, max(K, 3)).

    Rows: ambient*I, diffuse*I, specular*I, specular power (per structure); then the world unit
    vectors towards the light ``L``, the half vector ``H`` and the view direction ``V``.
    """
    try:
        d = np.asarray(direction, dtype=np.float64)
    except (TypeError, ValueError):
        d = np.zeros(0)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or not np.any(d):
        raise DVRInputError(
            f"light_direction: expected a non-zero (x, y, z) in camera coordinates, got {direction}"
        )
    if not (math.isfinite(float(intensity)) and float(intensity) >= 0):
        raise DVRInputError(f"rendering.light_intensity: must be a number >= 0, got {intensity}")
    fwd, right, up = camera.basis()
    lw = d[0] * right + d[1] * up - d[2] * fwd
    lw /= np.linalg.norm(lw)
    h = lw - fwd
    hn = np.linalg.norm(h)
    h = h / hn if hn > 1e-12 else lw
    k = len(mats)
    out = np.zeros((7, max(k, 3)))
    inten = float(intensity)
    out[0, :k] = [m.ambient * inten for m in mats]
    out[1, :k] = [m.diffuse * inten for m in mats]
    out[2, :k] = [m.specular * inten for m in mats]
    out[3, :k] = [m.specular_power for m in mats]
    out[4, :3], out[5, :3], out[6, :3] = lw, h, fwd
    return out


_DIRECTIONS: list = []
#: Shading values are stored as ``round(x * _SHADE_SCALE)`` (uint16; 65535 is kept free).
_SHADE_SCALE = 65534.0
#: Recent shading tables by :func:`shading_key` (a few MB each at most; read-only).
_SHADING_MEMO: dict = {}


def shading_table(light: np.ndarray, k: int) -> np.ndarray:
    """Per structure and normal code: lit diffuse cosine and specular power (uint16 (K, 65536, 2)).

    VTK's ``BuildShadingTable`` for the decoded directions of
    :func:`dvr_perception.rays._grid.code_directions` with two-sided lighting (a normal facing
    away from the viewer is flipped): ``[max(n.L, 0), (n.H) ** p]``, the specular entry only
    where ``n.L > 0`` and ``n.H > 0.001``.  The kernels interpolate the 8 corners' entries and
    shade with ``ka I + kd I diffuse`` and ``ks I specular`` (so only the light, the view and
    the specular powers enter the table).  Values are stored as ``round(x * 65534)`` (like
    VTK's 15-bit tables, half the cache footprint of float32).
    """
    key = shading_key(light, k)
    hit = _SHADING_MEMO.get(key)
    if hit is not None:
        return hit
    geo = _light_columns(light)
    out = np.zeros((k, len(geo["diffuse"]), 2), np.uint16)
    out[:, :, 0] = geo["diffuse"]
    for s in range(k):
        out[s, :, 1] = _specular_column(geo, float(light[3, s]))
    out.flags.writeable = False
    if len(_SHADING_MEMO) >= 8:
        _SHADING_MEMO.pop(next(iter(_SHADING_MEMO)), None)
    _SHADING_MEMO[key] = out
    return out


#: Per light geometry (light, half vector, view): the diffuse column and the specular
#: columns by power (an optimiser changes one structure's power at a time).
_LIGHT_MEMO: dict = {}


def _light_columns(light: np.ndarray) -> dict:
    """Return the power-independent part of :func:`shading_table` for ``light``'s geometry."""
    key = light[4:7, :3].tobytes()
    geo = _LIGHT_MEMO.get(key)
    if geo is not None:
        return geo
    if not _DIRECTIONS:
        from dvr_perception.rays._grid import code_directions

        _DIRECTIONS.append(code_directions())
    d = _DIRECTIONS[0]
    sign = np.where(d @ light[6, :3] > 0.0, -1.0, 1.0)
    ndl = sign * (d @ light[4, :3])
    ndh = sign * (d @ light[5, :3])
    lit = ndl > 0.0
    on = lit & (ndh > 0.001)
    geo = {
        "diffuse": np.floor(np.where(lit, ndl, 0.0) * _SHADE_SCALE + 0.5).astype(np.uint16),
        "on": on,
        "x": np.where(on, ndh, 0.0),
        "specular": {},
    }
    if len(_LIGHT_MEMO) >= 4:
        _LIGHT_MEMO.pop(next(iter(_LIGHT_MEMO)), None)
    _LIGHT_MEMO[key] = geo
    return geo


def _specular_column(geo: dict, power: float) -> np.ndarray:
    """Return the specular column of :func:`shading_table` for one power (uint16, kept)."""
    col = geo["specular"].get(power)
    if col is None:
        spec = np.where(geo["on"], np.power(geo["x"], power), 0.0)
        col = np.floor(np.minimum(spec, 1.0) * _SHADE_SCALE + 0.5).astype(np.uint16)
        if len(geo["specular"]) >= 24:
            geo["specular"].pop(next(iter(geo["specular"])), None)
        geo["specular"][power] = col
    return col


def shading_key(light: np.ndarray, k: int) -> bytes:
    """Return what :func:`shading_table` depends on (light, half vector, view, powers)."""
    return np.concatenate([[k], light[3, :k], light[4:7, :3].ravel()]).tobytes()


def stale_structures(old: bytes, new: bytes) -> np.ndarray | None:
    """Structures whose rows of :func:`shading_table` differ between two :func:`shading_key`.

    ``None`` when the light, half vector or view changed (every row differs), else a (K,)
    bool array: the structures whose specular power changed.

    Examples
    --------
    >>> import numpy as np
    >>> light = np.zeros((7, 3))
    >>> light[3], light[4:7, 2] = (8.0, 16.0, 32.0), 1.0
    >>> other = light.copy()
    >>> other[3, 1] = 20.0
    >>> stale_structures(shading_key(light, 3), shading_key(other, 3)).tolist()
    [False, True, False]
    >>> other[4, :] = (0.6, 0.0, 0.8)
    >>> stale_structures(shading_key(light, 3), shading_key(other, 3)) is None
    True
    """
    a, b = np.frombuffer(old, np.float64), np.frombuffer(new, np.float64)
    if a.size != b.size or a.size == 0 or a[0] != b[0]:
        return None
    k = int(a[0])
    if not np.array_equal(a[1 + k :], b[1 + k :]):
        return None
    return a[1 : 1 + k] != b[1 : 1 + k]
