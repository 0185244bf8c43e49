"""The :class:`Volume` container shared by every stage of the pipeline."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = ["Volume"]


@dataclass(frozen=True, eq=False)
class Volume:
    """A scalar volume on a regular grid.

    Parameters
    ----------
    data : numpy.ndarray
        3-D array indexed ``[z, y, x]`` (x varies fastest, as in raw files and VTK point order).
    spacing : tuple of float
        Voxel size along x, y, z in world units.
    origin : tuple of float
        World position of voxel ``[0, 0, 0]``.
    direction : array-like, optional
        3 x 3 orthonormal matrix whose columns are the world (patient LPS) directions of the
        x, y and z index axes, as ITK/DICOM/Slicer store it; default the identity.  Loaders
        turn axis-aligned flips and permutations into the data order
        (:func:`dvr_perception.volume.orient.canonical`), so only an oblique volume keeps a
        non-identity matrix.  Voxel ``[k, j, i]`` lies at world
        ``origin + direction @ (spacing * (i, j, k))``.
    name : str
        Short name used in titles and output file names.
    source : str
        Where the volume came from (a path or ``"phantom"``).
    oriented : bool
        Whether the patient orientation is known: ``False`` when the file it was read from
        records none (an NRRD without ``space``, headerless raw, legacy ``.vtk``, a ``.vti``
        without ``Direction``...), whose axes were then taken as L, P, S.  Default ``True``
        (an in-memory volume means what its direction says); re-ordering with
        :func:`dvr_perception.volume.orient.reorient` sets it.

    Examples
    --------
    >>> import numpy as np
    >>> vol = Volume(np.zeros((2, 3, 4), np.uint8), spacing=(1.0, 1.0, 2.0))
    >>> vol.dims
    (4, 3, 2)
    >>> vol.bounds
    (0.0, 3.0, 0.0, 2.0, 0.0, 2.0)
    """

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "volume"
    source: str = ""
    labels: np.ndarray | None = field(default=None, repr=False)
    direction: tuple[tuple[float, float, float], ...] = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    oriented: bool = True

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if data.ndim != 3:
            raise DVRInputError(f"volume {self.name!r}: data must be 3-D, got shape {data.shape}")
        if data.size == 0 or min(data.shape) < 2:
            raise DVRInputError(
                f"volume {self.name!r}: every dimension must have at least 2 voxels, "
                f"got shape (z, y, x) = {data.shape}"
            )
        if data.dtype.kind not in "uif" or data.dtype.itemsize > 8:
            raise DVRInputError(
                f"volume {self.name!r}: unsupported dtype {data.dtype}; expected an integer "
                "or floating-point scalar type"
            )
        if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
            bad = int(np.count_nonzero(~np.isfinite(data)))
            raise DVRInputError(
                f"volume {self.name!r}: {bad} voxel(s) are NaN or infinite; expected finite values"
            )
        spacing = tuple(float(s) for s in self.spacing)
        origin = tuple(float(o) for o in self.origin)
        if len(spacing) != 3 or not all(np.isfinite(s) and 0 < s <= 1e6 for s in spacing):
            raise DVRInputError(
                f"volume {self.name!r}: spacing must be three numbers in (0, 1e6], got "
                f"{self.spacing}"
            )
        if len(origin) != 3 or not all(np.isfinite(o) for o in origin):
            raise DVRInputError(
                f"volume {self.name!r}: origin must be three finite numbers, got {self.origin}"
            )
        if self.labels is not None:
            labels = np.asarray(self.labels)
            if labels.shape != data.shape or labels.dtype.kind not in "ui":
                raise DVRInputError(
                    f"volume {self.name!r}: label volume must be an integer array of shape "
                    f"{data.shape}, got {labels.dtype} {labels.shape}"
                )
            object.__setattr__(self, "labels", np.ascontiguousarray(labels))
        object.__setattr__(self, "direction", _check_direction(self.direction, self.name))
        if not data.dtype.isnative:  # e.g. nibabel's big-endian MGH data: VTK needs native
            data = data.astype(data.dtype.newbyteorder("="))
        object.__setattr__(self, "data", np.ascontiguousarray(data))
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "oriented", bool(self.oriented))

    @property
    def dims(self) -> tuple[int, int, int]:
        """Number of voxels along x, y, z (VTK order)."""
        z, y, x = self.data.shape
        return (x, y, z)

    @property
    def bounds(self) -> tuple[float, float, float, float, float, float]:
        """Bounds ``(xmin, xmax, ymin, ymax, zmin, zmax)`` of the voxel centres in the frame.

        The frame is ``origin + spacing * index`` -- world (patient LPS) coordinates unless
        the volume is :attr:`oblique`; the engine and cameras work in it.
        """
        out: list[float] = []
        for n, s, o in zip(self.dims, self.spacing, self.origin, strict=True):
            out += [o, o + (n - 1) * s]
        return tuple(out)  # type: ignore[return-value]

    @property
    def oblique(self) -> bool:
        """True when the direction matrix is not the identity (the volume is rotated)."""
        return not np.array_equal(np.asarray(self.direction), np.eye(3))

    def to_world(self, points) -> np.ndarray:
        """Map points of the volume frame (``origin + spacing * index``) to world (LPS).

        The engine renders in the volume frame; a camera placed in world coordinates is
        brought into it with :meth:`to_frame` (the direction matrix is a rotation, so
        distances and angles are kept).

        Examples
        --------
        >>> import numpy as np
        >>> d = ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        >>> v = Volume(np.zeros((2, 2, 2), np.uint8), origin=(1, 0, 0), direction=d)
        >>> v.to_world([2.0, 0.0, 0.0]).tolist()
        [1.0, 1.0, 0.0]
        """
        p = np.asarray(points, float)
        o = np.asarray(self.origin)
        return o + (p - o) @ np.asarray(self.direction).T

    def to_frame(self, points) -> np.ndarray:
        """Map world (LPS) points into the volume frame (the inverse of :meth:`to_world`)."""
        p = np.asarray(points, float)
        o = np.asarray(self.origin)
        return o + (p - o) @ np.asarray(self.direction)

    @property
    def center(self) -> tuple[float, float, float]:
        """Centre of the bounds (in the frame; :meth:`to_world` maps it to patient LPS)."""
        b = self.bounds
        return ((b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2)

    @property
    def scalar_range(self) -> tuple[float, float]:
        """Minimum and maximum voxel value."""
        return (float(self.data.min()), float(self.data.max()))


def _check_direction(direction, name: str) -> tuple[tuple[float, float, float], ...]:
    try:
        m = np.array(direction, dtype=float)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise DVRInputError(
            f"volume {name!r}: direction must be a 3 x 3 matrix of finite numbers, got "
            f"{str(direction)[:80]}"
        )
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-3) or np.linalg.det(m) < 0.5:
        if np.allclose(m.T @ m, np.eye(3), atol=1e-3):
            raise DVRInputError(
                f"volume {name!r}: direction is a reflection (determinant -1); expected a "
                "rotation (flip the data along one axis instead)"
            )
        raise DVRInputError(
            f"volume {name!r}: direction must be orthonormal (a rotation), got {m.tolist()}"
        )
    u, _, vt = np.linalg.svd(m)  # the nearest exact rotation (removes rounding)
    m = u @ vt
    m[np.abs(m) < 1e-12] = 0.0
    m[np.abs(np.abs(m) - 1) < 1e-12] = np.sign(m[np.abs(np.abs(m) - 1) < 1e-12])
    return tuple(tuple(float(v) for v in row) for row in m)
