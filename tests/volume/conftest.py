"""Fixtures for the volume tests: a minimal DICOM writer (explicit VR little endian).

Just enough tags for ``vtkDICOMImageReader``; VTK has no DICOM writer.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

_LONG_VRS = {"OB", "OW", "SQ", "UN", "UT"}


def _element(group: int, elem: int, vr: str, value: bytes) -> bytes:
    if len(value) % 2:
        value += b"\0" if vr in ("UI", "OB") else b" "
    head = struct.pack("<HH", group, elem) + vr.encode("ascii")
    if vr in _LONG_VRS:
        return head + b"\0\0" + struct.pack("<I", len(value)) + value
    return head + struct.pack("<H", len(value)) + value


def _text(values) -> bytes:
    return "\\".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values).encode()


def write_series(folder: Path, data: np.ndarray, *, spacing=(0.5, 0.75, 2.0), z0=10.0):
    """Write ``data[z, y, x]`` (uint16) as one file per slice; slice k at z = z0 + k*dz."""
    folder.mkdir(parents=True, exist_ok=True)
    nz, ny, nx = data.shape
    dx, dy, dz = spacing
    sop_class = b"1.2.840.10008.5.1.4.1.1.2"
    for k in range(nz):
        uid = f"1.2.826.0.1.3680043.2.1125.1.{k + 1}".encode()
        meta = b"".join(
            [
                _element(0x0002, 0x0001, "OB", b"\0\1"),
                _element(0x0002, 0x0002, "UI", sop_class),
                _element(0x0002, 0x0003, "UI", uid),
                _element(0x0002, 0x0010, "UI", b"1.2.840.10008.1.2.1"),
            ]
        )
        meta = _element(0x0002, 0x0000, "UL", struct.pack("<I", len(meta))) + meta
        body = b"".join(
            [
                _element(0x0008, 0x0016, "UI", sop_class),
                _element(0x0008, 0x0018, "UI", uid),
                _element(0x0008, 0x0060, "CS", b"CT"),
                _element(0x0018, 0x0050, "DS", _text([dz])),
                _element(0x0020, 0x000D, "UI", b"1.2.826.0.1.3680043.2.1125.2"),
                _element(0x0020, 0x000E, "UI", b"1.2.826.0.1.3680043.2.1125.3"),
                _element(0x0020, 0x0013, "IS", _text([k + 1])),
                _element(0x0020, 0x0032, "DS", _text([0.0, 0.0, z0 + k * dz])),
                _element(0x0020, 0x0037, "DS", _text([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])),
                _element(0x0028, 0x0002, "US", struct.pack("<H", 1)),
                _element(0x0028, 0x0004, "CS", b"MONOCHROME2"),
                _element(0x0028, 0x0010, "US", struct.pack("<H", ny)),
                _element(0x0028, 0x0011, "US", struct.pack("<H", nx)),
                _element(0x0028, 0x0030, "DS", _text([dy, dx])),
                _element(0x0028, 0x0100, "US", struct.pack("<H", 16)),
                _element(0x0028, 0x0101, "US", struct.pack("<H", 16)),
                _element(0x0028, 0x0102, "US", struct.pack("<H", 15)),
                _element(0x0028, 0x0103, "US", struct.pack("<H", 0)),
                _element(0x7FE0, 0x0010, "OW", data[k].astype("<u2").tobytes()),
            ]
        )
        (folder / f"slice{k:03d}.dcm").write_bytes(b"\0" * 128 + b"DICM" + meta + body)


@pytest.fixture
def dicom_writer():
    """Return :func:`write_series`."""
    return write_series
