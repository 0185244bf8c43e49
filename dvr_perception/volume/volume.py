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
    name : str
        Short name used in titles and output file names.
    source : str
        Where the volume came from (a path or ``"phantom"``).

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
        object.__setattr__(self, "data", np.ascontiguousarray(data))
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "origin", origin)

    @property
    def dims(self) -> tuple[int, int, int]:
        """Number of voxels along x, y, z (VTK order)."""
        z, y, x = self.data.shape
        return (x, y, z)

    @property
    def bounds(self) -> tuple[float, float, float, float, float, float]:
        """World bounds ``(xmin, xmax, ymin, ymax, zmin, zmax)`` of the voxel centres."""
        out: list[float] = []
        for n, s, o in zip(self.dims, self.spacing, self.origin, strict=True):
            out += [o, o + (n - 1) * s]
        return tuple(out)  # type: ignore[return-value]

    @property
    def center(self) -> tuple[float, float, float]:
        """World centre of the bounds."""
        b = self.bounds
        return ((b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2)

    @property
    def scalar_range(self) -> tuple[float, float]:
        """Minimum and maximum voxel value."""
        return (float(self.data.min()), float(self.data.max()))
