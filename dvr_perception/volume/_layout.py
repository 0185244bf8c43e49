"""The parsed header of a volume file (:class:`Layout`) and the exact, bounded reads.

Shared by the header parsers of :mod:`._metaimage`, :mod:`._legacy_vtk`, :mod:`._vti` and
:mod:`._nifti` (see :mod:`._headers` for why one parse serves the check and the read).
"""

from __future__ import annotations

import math
import warnings
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._limits import (
    check_ratio,
    parse_float,
    parse_int,
    shown,
)

__all__ = ["Layout", "read_layout"]

_CHUNK = 1 << 20


@dataclass
class Layout:
    """What one parse of a header says about the volume, and how to read its voxels.

    Attributes
    ----------
    path : pathlib.Path
        The header file.
    dims : tuple of int
        Points along x, y, z.
    dtype : numpy.dtype
        The voxel type as stored (byte order included).
    nbytes : int
        Bytes of every array a VTK reader of the file would allocate (the memory budget).
    axes : numpy.ndarray
        3 x 3, columns: world vector of one step along index x, y, z.
    origin : numpy.ndarray
        World position of the first voxel.
    oriented : bool
        Whether the file records a patient orientation.
    data_file : pathlib.Path
        The file holding the voxels (``path`` for attached data).
    reader : callable
        Returns the voxels as a flat array of ``dtype`` (``dims`` product values).
    """

    path: Path
    dims: tuple[int, int, int]
    dtype: np.dtype
    nbytes: int
    axes: np.ndarray
    origin: np.ndarray
    oriented: bool
    data_file: Path
    reader: Callable[[], np.ndarray] = field(repr=False)


def read_layout(layout: Layout) -> np.ndarray:
    """Return the voxels of ``layout`` as ``data[z, y, x]`` in native byte order."""
    flat = layout.reader()
    count = math.prod(layout.dims)
    if flat.size != count:  # a reader's own bug, never the file's: still one clear error
        raise DVRInputError(f"{layout.path}: read {flat.size} values, expected {count}")
    data = flat.reshape(layout.dims[::-1])
    return data.astype(data.dtype.newbyteorder("="), copy=False)


# -- helpers ---------------------------------------------------------------------------------


def _read_exact(src: Path, offset: int, count: int, where) -> bytes:
    """Read exactly ``count`` bytes of ``src`` from ``offset``; refuse a shorter file."""
    size = src.stat().st_size
    if offset < 0 or size - offset < count:
        raise DVRInputError(
            f"{where}: truncated: expected {count} bytes from offset {offset}, found "
            f"{max(size - max(offset, 0), 0)}"
        )
    with open(src, "rb") as f:
        f.seek(offset)
        blob = f.read(count)
    if len(blob) != count:
        raise DVRInputError(f"{where}: truncated: expected {count} bytes, read {len(blob)}")
    return blob


def _raw_array(src: Path, offset: int, dtype: np.dtype, count: int, where) -> np.ndarray:
    """``count`` values of ``dtype`` stored from ``offset`` of ``src`` (every byte checked)."""
    nbytes = count * dtype.itemsize
    size = src.stat().st_size
    if offset < 0 or size - offset < nbytes:
        raise DVRInputError(
            f"{where}: truncated: expected {nbytes} bytes of voxel data from offset {offset}, "
            f"found {max(size - max(offset, 0), 0)}"
        )
    out = np.empty(count, dtype)
    view = memoryview(out.view(np.uint8).reshape(-1))
    got = 0
    with open(src, "rb") as f:
        f.seek(offset)
        while got < nbytes:
            n = f.readinto(view[got : min(got + _CHUNK, nbytes)])
            if not n:
                break
            got += n
    if got != nbytes:
        raise DVRInputError(f"{where}: truncated: expected {nbytes} bytes, read {got}")
    return out


def _inflate(blob, expected: int, where, what: str = "zlib") -> bytes:
    """Decompress zlib/gzip ``blob`` into exactly ``expected`` bytes (never more)."""
    if expected <= 0:
        raise DVRInputError(f"{where}: no {what} data expected")
    check_ratio(where, len(blob), expected)
    engine = zlib.decompressobj(47)  # zlib or gzip header, detected
    try:
        out = engine.decompress(blob, expected)
        extra = engine.unconsumed_tail and engine.decompress(engine.unconsumed_tail, 1)
    except zlib.error as exc:
        raise DVRInputError(f"{where}: corrupt {what} data ({exc})") from None
    if len(out) < expected:
        raise DVRInputError(
            f"{where}: truncated: the {what} data expands to {len(out)} bytes, the header's "
            f"sizes need {expected}"
        )
    if extra:
        raise DVRInputError(
            f"{where}: the {what} data expands to more than the {expected} bytes the header's "
            "sizes need"
        )
    return out


def _bool(value: str, where, name: str) -> bool:
    low = value.strip().lower()
    if low in ("true", "1"):
        return True
    if low in ("false", "0"):
        return False
    raise DVRInputError(f"{where}: field {name!r}: expected True or False, got {shown(value)}")


def _floats(value: str, n: int, where, name: str) -> list[float]:
    vals = value.split()
    if len(vals) != n:
        raise DVRInputError(f"{where}: field {name!r}: expected {n} numbers, got {shown(value)}")
    return [parse_float(v, where, name) for v in vals]


def _ints(value: str, n: int, where, name: str, lo: int = 1) -> list[int]:
    vals = value.split()
    if len(vals) != n:
        raise DVRInputError(f"{where}: field {name!r}: expected {n} integers, got {shown(value)}")
    return [parse_int(v, where, name, lo=lo) for v in vals]


def _ascii_values(text: str, dtype: np.dtype, count: int, where, field_name: str):
    """Parse exactly ``count`` whitespace-separated numbers (nothing else) into ``dtype``."""
    parse = np.float64 if dtype.kind == "f" else np.int64
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            vals = np.fromstring(text, dtype=parse, sep=" ")
        except (ValueError, DeprecationWarning):
            vals = None
    if vals is None or vals.size != count:
        got = "unreadable numbers" if vals is None else f"{vals.size} numbers"
        raise DVRInputError(
            f"{where}: field {field_name!r}: truncated or malformed ASCII data: expected {count} "
            f"numbers, got {got}"
        )
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        if vals.size and (vals.min() < info.min or vals.max() > info.max):
            raise DVRInputError(f"{where}: field {field_name!r}: values outside {dtype.name}")
    return vals.astype(dtype)
