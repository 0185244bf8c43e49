"""NIfTI-1 and NIfTI-2 headers, checked exactly as ``vtkNIFTIImageReader`` parses them.

Part of the one-parse header checks: see :mod:`dvr_perception.volume._headers`.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._layout import (
    _CHUNK,
)
from dvr_perception.volume._limits import (
    check_budget,
    check_ratio,
)

__all__ = ["NIFTI_TYPES", "check_nifti"]

# -- NIfTI (read by VTK: checked exactly as vtkNIFTIImageReader parses it) -------------------

#: NIfTI ``datatype`` codes VTK reads as one scalar component, and their numpy types.
NIFTI_TYPES = {2: "u1", 4: "i2", 8: "i4", 16: "f4", 64: "f8", 256: "i1", 512: "u2",
               768: "u4", 1024: "i8", 1280: "u8"}  # fmt: skip
#: Multi-component codes (complex, RGB, RGBA) VTK reads: refused (a scalar volume is needed).
_NIFTI_VECTOR = {32: "complex64", 1792: "complex128", 128: "RGB24", 2304: "RGBA32"}


def _nifti_stream(path: Path, gz: bool):
    import gzip

    return gzip.open(path, "rb") if gz else open(path, "rb")


def check_nifti(path: Path, ext: str, *, limit: int | None = None, hint: str | None = None):
    """Check a NIfTI-1 or NIfTI-2 file as ``vtkNIFTIImageReader`` reads it; return its sizes.

    The version comes from the magic (``n+1``/``ni1`` at byte 344, ``n+2``/``ni2`` at byte 4,
    as VTK decides), the byte order from ``dim[0]``, the voxel type and components from
    ``datatype`` (never ``bitpix``).  Refused: an Analyze or unknown header, sizes outside
    VTK's range, a multi-component type or vector dimension, a ``vox_offset`` that is not a
    finite whole number of bytes, sizes over the memory limit, and data (decompressed) shorter
    than ``vox_offset`` plus the first volume.  Returns ``(dims, dtype)``.
    """
    import gzip
    import struct

    gz = ext == ".nii.gz"
    try:
        with _nifti_stream(path, gz) as f:
            head = f.read(540)
    except (OSError, EOFError, zlib.error) as exc:
        raise DVRInputError(f"{path}: cannot read the NIfTI header ({exc})") from None
    if len(head) < 348:
        raise DVRInputError(f"{path}: truncated: the NIfTI header needs 348 bytes")
    version = 0
    if head[4:5] == b"n" and head[5:6] in (b"+", b"i") and head[6:7] in b"23456789" \
            and head[7:8] == b"\0":  # fmt: skip
        version = 2
        if head[8:12] != b"\r\n\x1a\n":
            raise DVRInputError(f"{path}: field 'magic': NIfTI-2 header corrupted by newline "
                                "conversion")  # fmt: skip
        if head[6:7] != b"2":
            raise DVRInputError(f"{path}: field 'magic': NIfTI version {head[6:7].decode()}")
    elif head[344:345] == b"n" and head[345:346] in (b"+", b"i") and head[346:348] == b"1\0":
        version = 1
    if version == 0:
        raise DVRInputError(
            f"{path}: field 'magic': not a NIfTI-1 or NIfTI-2 header (Analyze 7.5 and other "
            "files are not read)"
        )
    if version == 2 and len(head) < 540:
        raise DVRInputError(f"{path}: truncated: the NIfTI-2 header needs 540 bytes")
    code = "q" if version == 2 else "h"
    dim_at = 16 if version == 2 else 40
    order = "<"
    if not 0 <= struct.unpack_from("<" + code, head, dim_at)[0] <= 7:
        order = ">"
    dim = list(struct.unpack_from(order + "8" + code, head, dim_at))
    ndim = dim[0]
    if not 0 <= ndim <= 7:
        raise DVRInputError(f"{path}: NIfTI field 'dim': dim[0] = {ndim}; expected 0 to 7")
    for i in range(1, 8):
        if i > ndim:
            dim[i] = 1
        elif not 0 <= dim[i] <= 2**31 - 1:
            raise DVRInputError(f"{path}: NIfTI field 'dim': dim[{i}] = {dim[i]} is out of range")
    dt_at = 12 if version == 2 else 70
    (datatype,) = struct.unpack_from(order + "h", head, dt_at)
    if datatype in _NIFTI_VECTOR:
        raise DVRInputError(
            f"{path}: NIfTI field 'datatype': {_NIFTI_VECTOR[datatype]} voxels; expected a "
            "scalar type"
        )
    if datatype not in NIFTI_TYPES:
        raise DVRInputError(f"{path}: NIfTI field 'datatype': unsupported code {datatype}")
    if ndim >= 5 and dim[5] != 1:
        raise DVRInputError(
            f"{path}: NIfTI field 'dim': dim[5] = {dim[5]} vector components; expected a "
            "scalar volume"
        )
    dims = (dim[1], dim[2], dim[3])
    if min(dims) < 1:
        raise DVRInputError(f"{path}: the volume is empty (NIfTI dim {dim[1:4]})")
    dtype = np.dtype(NIFTI_TYPES[datatype]).newbyteorder(order)
    nbytes = check_budget(path, dims, dtype, "dim", limit=limit, hint=hint)
    (vox,) = struct.unpack_from(order + ("q" if version == 2 else "f"), head,
                                168 if version == 2 else 108)  # fmt: skip
    if not (math.isfinite(vox) and 0 <= vox < 2**40):
        raise DVRInputError(f"{path}: NIfTI field 'vox_offset': {vox} is not a byte offset")
    need = int(vox) + nbytes  # VTK reads the first volume (time point) from vox_offset
    if gz:
        if need > 1100 * path.stat().st_size + 4096:
            check_ratio(str(path), path.stat().st_size, need)
        got = 0
        try:
            with gzip.open(path, "rb") as f:
                while got < need:
                    piece = f.read(min(_CHUNK, need - got))
                    if not piece:
                        break
                    got += len(piece)
        except (OSError, EOFError, zlib.error) as exc:
            raise DVRInputError(f"{path}: corrupt gzip data ({exc})") from None
    else:
        got = min(path.stat().st_size, need)
    if got < need:
        raise DVRInputError(
            f"{path}: truncated: vox_offset {int(vox)} plus {nbytes} bytes of voxel data (dim "
            f"{dims}) need {need} bytes, the file holds {got}"
        )
    return dims, dtype
