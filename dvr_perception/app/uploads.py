"""Safety checks of an uploaded volume file, before any reader sees it.

A hostile upload may name a *detached* data file anywhere on the server (``data file:`` in a
NRRD header, ``ElementDataFile`` in a MetaImage header), or be a small compressed file whose
voxel data expands to gigabytes.  :func:`check_volume_bytes` refuses both without reading any
other file and without holding the decompressed data: it reads the header's dimensions and
voxel type, checks the voxel data they claim against a limit, and streams any compressed data
through a bounded decompressor, counting (and dropping) the bytes, to check that it holds
exactly what the header claims.  Only then is the file handed to the volume reader.
"""

from __future__ import annotations

import math
import re
import struct
import zlib

from dvr_perception.errors import DVRInputError

__all__ = ["check_volume_bytes"]

#: Bytes decompressed per step by the bounded decompressor.
STEP_BYTES = 1 << 20
#: Largest header read (NRRD, MetaImage, VTI).
HEADER_BYTES = 65536

_NRRD_SIZES = {
    1: ("signed char", "int8", "int8_t", "uchar", "unsigned char", "uint8", "uint8_t"),
    2: (
        "short",
        "short int",
        "signed short",
        "signed short int",
        "int16",
        "int16_t",
        "ushort",
        "unsigned short",
        "unsigned short int",
        "uint16",
        "uint16_t",
    ),
    4: ("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t"),
    8: (
        "longlong",
        "long long",
        "long long int",
        "signed long long",
        "int64",
        "int64_t",
        "ulonglong",
        "unsigned long long",
        "unsigned long long int",
        "uint64",
        "uint64_t",
        "double",
    ),
}
_NRRD_SIZES[4] += ("float",)
_NRRD_TYPE_BYTES = {alias: n for n, names in _NRRD_SIZES.items() for alias in names}
_MET_TYPE_BYTES = {
    "MET_CHAR": 1,
    "MET_UCHAR": 1,
    "MET_SHORT": 2,
    "MET_USHORT": 2,
    "MET_INT": 4,
    "MET_UINT": 4,
    "MET_LONG": 4,
    "MET_ULONG": 4,
    "MET_LONG_LONG": 8,
    "MET_ULONG_LONG": 8,
    "MET_FLOAT": 4,
    "MET_DOUBLE": 8,
}
_VTK_TYPE_BYTES = {
    "Int8": 1,
    "UInt8": 1,
    "Int16": 2,
    "UInt16": 2,
    "Int32": 4,
    "UInt32": 4,
    "Int64": 8,
    "UInt64": 8,
    "Float32": 4,
    "Float64": 8,
}
_NIFTI_HEADER = 348
_MAX_DIM = 1 << 20


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def _claimed(name: str, dims, item: int, limit: int) -> int:
    """Return the voxel bytes ``dims`` x ``item`` claim; refuse them above ``limit``."""
    if not dims or any(not 0 < d <= _MAX_DIM for d in dims) or not 0 < item <= 64:
        raise DVRInputError(f"upload {name}: bad dimensions {tuple(dims)} or voxel size {item}")
    total = math.prod(dims) * item
    if total > limit:
        raise DVRInputError(
            f"upload {name}: the header claims {_mb(total)} of voxel data, more than the limit "
            f"of {_mb(limit)} (--max-volume-mb)"
        )
    return total


def _inflated_size(name: str, payload: bytes, expected: int) -> int:
    """Count the bytes gzip/zlib ``payload`` inflates to; refuse it once beyond ``expected``.

    Concatenated members are followed; at most :data:`STEP_BYTES` of inflated data is held at
    a time, so a small file that expands to gigabytes costs no memory.
    """
    view = memoryview(payload)
    total, pos, piece = 0, 0, b""
    engine = zlib.decompressobj(47)  # a gzip or zlib header, detected
    while True:
        if not piece and pos < len(view):
            piece = view[pos : pos + STEP_BYTES]
            pos += len(piece)
        try:
            out = engine.decompress(piece, STEP_BYTES)
        except zlib.error as exc:
            raise DVRInputError(f"upload {name}: corrupt gzip data ({exc})") from None
        total += len(out)
        if total > expected:
            raise DVRInputError(
                f"upload {name}: the compressed data expands beyond the {_mb(expected)} its "
                "header claims; refused"
            )
        piece = engine.unconsumed_tail
        if engine.eof:  # one member done: the next (if any) starts after it
            pos -= len(engine.unused_data)
            piece = b""
            if not bytes(view[pos:]).strip(b"\0"):
                return total
            engine = zlib.decompressobj(47)
        elif not piece and pos >= len(view) and not out:
            raise DVRInputError(f"upload {name}: truncated gzip data")


def _header_lines(content: bytes, name: str) -> tuple[list[str], int]:
    """Split a text header (up to the first blank line) and return it with the data offset."""
    head = content[:HEADER_BYTES]
    end = head.find(b"\n\n")
    end_crlf = head.find(b"\r\n\r\n")
    if end < 0 and end_crlf < 0:
        return head.decode("latin-1").splitlines(), len(content)
    if end < 0 or 0 <= end_crlf < end:
        return head[:end_crlf].decode("latin-1").splitlines(), end_crlf + 4
    return head[:end].decode("latin-1").splitlines(), end + 2


def _check_nrrd(name: str, content: bytes, limit: int) -> None:
    if not content.startswith(b"NRRD000"):
        raise DVRInputError(f"upload {name}: not a readable volume (no 'NRRD000X' magic line)")
    lines, offset = _header_lines(content, name)
    fields = {}
    for line in lines[1:]:
        if line.startswith("#") or ":=" in line:
            continue
        key, sep, value = line.partition(":")
        if sep:
            fields[key.strip().lower()] = value.strip()
    if "data file" in fields or "datafile" in fields:
        raise DVRInputError(
            f"upload {name}: the header names a detached data file; upload a single-file volume "
            "with its data attached"
        )
    try:
        dims = [int(v) for v in fields.get("sizes", "").split()]
    except ValueError:
        dims = []
    item = _NRRD_TYPE_BYTES.get(" ".join(fields.get("type", "").lower().split()), 0)
    expected = _claimed(name, dims, item, limit)
    encoding = fields.get("encoding", "raw").lower()
    if encoding in ("gzip", "gz"):
        _inflated_size(name, content[offset:], expected)
    elif encoding != "raw":
        raise DVRInputError(f"upload {name}: NRRD encoding {encoding!r}; expected raw or gzip")


def _check_mha(name: str, content: bytes, limit: int) -> None:
    head = content[:HEADER_BYTES]
    fields, offset = {}, 0
    for raw in head.split(b"\n"):
        offset += len(raw) + 1
        key, sep, value = raw.decode("latin-1").partition("=")
        if not sep:
            raise DVRInputError(
                f"upload {name}: not a readable volume (MetaImage header line {raw[:60]!r})"
            )
        fields[key.strip().lower()] = value.strip()
        if key.strip().lower() == "elementdatafile":
            break
    else:
        raise DVRInputError(f"upload {name}: MetaImage header without ElementDataFile")
    if fields["elementdatafile"] != "LOCAL":
        raise DVRInputError(
            f"upload {name}: the header names a detached data file; upload a single-file volume "
            "(ElementDataFile = LOCAL)"
        )
    try:
        dims = [int(v) for v in fields.get("dimsize", "").split()]
        channels = int(fields.get("elementnumberofchannels", "1"))
    except ValueError:
        dims, channels = [], 0
    item = _MET_TYPE_BYTES.get(fields.get("elementtype", "").upper(), 0) * channels
    expected = _claimed(name, dims, item, limit)
    if fields.get("compresseddata", "false").lower() == "true":
        _inflated_size(name, content[offset:], expected)


def _check_nifti(name: str, content: bytes, limit: int) -> None:
    if name.lower().endswith(".gz"):
        # the whole file is one gzip stream: bound it by the largest header + data allowed
        try:
            head = zlib.decompressobj(47).decompress(content[: 1 << 16], _NIFTI_HEADER)
        except zlib.error:
            raise DVRInputError(f"upload {name}: not a readable volume (not gzip data)") from None
    else:
        head = content[:_NIFTI_HEADER]
    if len(head) < _NIFTI_HEADER:
        raise DVRInputError(f"upload {name}: not a readable volume (shorter than a NIfTI header)")
    for order in "<>":
        (size,) = struct.unpack_from(order + "i", head, 0)
        if size == _NIFTI_HEADER:
            break
    else:
        raise DVRInputError(f"upload {name}: not a readable volume (no NIfTI-1 header size)")
    dim = struct.unpack_from(order + "8h", head, 40)
    (bitpix,) = struct.unpack_from(order + "h", head, 72)
    (vox_offset,) = struct.unpack_from(order + "f", head, 108)
    if not 1 <= dim[0] <= 7 or bitpix <= 0 or bitpix % 8:
        raise DVRInputError(f"upload {name}: bad NIfTI dimensions {dim} or bitpix {bitpix}")
    expected = _claimed(name, dim[1 : 1 + dim[0]], bitpix // 8, limit)
    if name.lower().endswith(".gz"):
        extra = max(int(vox_offset), _NIFTI_HEADER) if math.isfinite(vox_offset) else 0
        _inflated_size(name, content, expected + min(extra, HEADER_BYTES))


def _check_vti(name: str, content: bytes, limit: int) -> None:
    head = content[:HEADER_BYTES].decode("latin-1")
    if "<VTKFile" not in head:
        raise DVRInputError(f"upload {name}: not a readable volume (no <VTKFile> element)")
    if re.search(r"\bcompressor\s*=", head):
        raise DVRInputError(
            f"upload {name}: compressed VTI files are not accepted as uploads; save it "
            "uncompressed or as .nrrd (gzip)"
        )
    m = re.search(r'WholeExtent\s*=\s*"([^"]*)"', head)
    try:
        ext = [int(v) for v in m.group(1).split()] if m else []
    except ValueError:
        ext = []
    if len(ext) != 6:
        raise DVRInputError(f"upload {name}: VTI without a valid WholeExtent")
    dims = [ext[1] - ext[0] + 1, ext[3] - ext[2] + 1, ext[5] - ext[4] + 1]
    arrays = re.findall(r"<DataArray\b[^>]*>", head)
    item = 0
    for tag in arrays:
        t = re.search(r'type\s*=\s*"(\w+)"', tag)
        c = re.search(r'NumberOfComponents\s*=\s*"(\d+)"', tag)
        item += _VTK_TYPE_BYTES.get(t.group(1) if t else "", 8) * int(c.group(1) if c else 1)
    _claimed(name, dims, max(item, 1), limit)


def check_volume_bytes(name: str, content: bytes, *, max_volume_bytes: int) -> None:
    """Refuse an uploaded file that names another file or holds too much voxel data.

    Parameters
    ----------
    name : str
        The file's name (its suffix says the format).
    content : bytes
        The uploaded bytes.
    max_volume_bytes : int
        Largest voxel data, decompressed, the file may claim and hold.

    Raises
    ------
    DVRInputError
        One line naming the upload and the reason.
    """
    low = name.lower()
    if low.endswith((".nhdr", ".mhd")):
        raise DVRInputError(
            f"upload {name}: a detached header needs its data file; upload a single-file volume "
            "(.nrrd, .mha, .vti, .nii, .nii.gz) instead"
        )
    if low.endswith(".nrrd"):
        _check_nrrd(name, content, max_volume_bytes)
    elif low.endswith(".mha"):
        _check_mha(name, content, max_volume_bytes)
    elif low.endswith((".nii", ".nii.gz")):
        _check_nifti(name, content, max_volume_bytes)
    elif low.endswith(".vti"):
        _check_vti(name, content, max_volume_bytes)
