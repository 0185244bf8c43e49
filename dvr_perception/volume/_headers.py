"""One parse of a MetaImage, VTK XML image data or legacy VTK header, then our own read.

A check in front of another program's reader is only as good as the agreement between the two
parsers, and every difference is a way through (a key in another case, a repeated key, an XML
comment, a later ``DIMENSIONS`` line).  So for MetaImage (``.mha``/``.mhd``), ``.vti`` and
legacy structured points (``.vtk``) the header is parsed *once*, here, into a :class:`Layout`
(sizes, type, byte order, encoding, which file and where its data lies, geometry), and the
voxels are read by :func:`read_layout` from that layout alone: VTK never opens the file.

The parse is also strict, so that a header it accepts means the same to VTK's readers (which
ParaView's MPI ranks still use, see ``dvr-perception pvbatch --ranks``): a key repeated in any
case, a known MetaImage key in another case, two synonyms of one field, a legacy keyword twice
or one the structured-points reader does not take, an XML comment, processing instruction,
``DOCTYPE`` or ``CDATA`` section, a second piece, a DataArray of unknown type or format, and an
unsupported compressor are each refused with one :class:`~dvr_perception.errors.DVRInputError`
naming the file and the field.

Data must be complete: a file (or a compressed stream) that holds fewer bytes than the header
claims is refused, and a buffer is only handed on once every byte of it has been written.
Every array a VTK reader would allocate counts against the memory limit.
"""

from __future__ import annotations

import base64
import binascii
import math
import re
import warnings
import xml.etree.ElementTree as ET
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._limits import (
    HEADER_MAX,
    check_budget,
    check_ratio,
    check_spacing,
    parse_float,
    parse_int,
    resolve_data_file,
    shown,
)

__all__ = ["Layout", "check_nifti", "legacy_layout", "meta_layout", "read_layout", "vti_layout"]

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


# -- MetaImage -------------------------------------------------------------------------------

#: MetaIO's element types: numpy type (byte order added from the header).  ``MET_LONG`` is 4
#: bytes in MetaIO's size table (VTK's reader allocates a C ``long`` for it, 8 bytes, and
#: leaves half of them unread; we read what MetaIO writes).
META_TYPES = {
    "MET_CHAR": "i1", "MET_UCHAR": "u1", "MET_SHORT": "i2", "MET_USHORT": "u2",
    "MET_INT": "i4", "MET_UINT": "u4", "MET_LONG": "i4", "MET_ULONG": "u4",
    "MET_LONG_LONG": "i8", "MET_ULONG_LONG": "u8", "MET_FLOAT": "f4", "MET_DOUBLE": "f8",
}  # fmt: skip
#: The keys MetaIO knows for an image (it matches them case-sensitively).
_META_KEYS = (
    "Comment", "ObjectType", "ObjectSubType", "TransformType", "NDims", "Name", "ID",
    "ParentID", "CompressedData", "CompressedDataSize", "BinaryData", "BinaryDataByteOrderMSB",
    "ElementByteOrderMSB", "Color", "Position", "Origin", "Offset", "Orientation", "Rotation",
    "TransformMatrix", "CenterOfRotation", "AnatomicalOrientation", "ElementSpacing",
    "ElementSize", "DimSize", "HeaderSize", "HeaderSizePerSlice", "Modality", "SequenceID",
    "ElementMin", "ElementMax", "ElementNumberOfChannels", "ElementType", "ElementDataFile",
    "AcquisitionDate", "DistanceUnits",
)  # fmt: skip
_META_CANON = {k.lower(): k for k in _META_KEYS}
#: Fields MetaIO reads as NDims numbers: NDims must come first.
_META_ARRAYS = ("DimSize", "ElementSpacing", "ElementSize", "Position", "Origin", "Offset",
                "Orientation", "Rotation", "TransformMatrix", "CenterOfRotation")  # fmt: skip
_META_SYNONYMS = (("Offset", "Position", "Origin"), ("TransformMatrix", "Rotation", "Orientation"),
                  ("BinaryDataByteOrderMSB", "ElementByteOrderMSB"))  # fmt: skip


def meta_fields(path: Path) -> tuple[dict[str, str], int]:
    """Return a MetaImage header's fields (keys as written) and the byte after its last line.

    The header ends with ``ElementDataFile`` (as in MetaIO).  Refused: a line without ``=``,
    a key repeated in any case, a known key in another case, two synonyms of one field, an
    array field before ``NDims``, a header longer than :data:`HEADER_MAX` bytes.
    """
    with open(path, "rb") as f:
        head = f.read(HEADER_MAX + 1)
    whole = len(head) <= HEADER_MAX
    fields: dict[str, str] = {}
    seen: dict[str, str] = {}
    pos = 0
    while "ElementDataFile" not in fields:
        if pos >= len(head):
            if whole:
                raise DVRInputError(f"{path}: MetaImage header has no 'ElementDataFile' field")
            raise DVRInputError(f"{path}: the MetaImage header is longer than {HEADER_MAX} bytes")
        nl = head.find(b"\n", pos)
        if nl < 0 and not whole:
            raise DVRInputError(f"{path}: the MetaImage header is longer than {HEADER_MAX} bytes")
        end = nl if nl >= 0 else len(head)
        line = head[pos:end].decode("latin-1").strip()
        pos = end + 1 if nl >= 0 else len(head)
        if not line:
            continue
        key, sep, value = line.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key:
            raise DVRInputError(f"{path}: malformed MetaImage header line {shown(line)}")
        low = key.lower()
        if low in seen:
            raise DVRInputError(
                f"{path}: field {key!r}: given twice (also as {seen[low]!r}); each MetaImage "
                "field may appear once"
            )
        seen[low] = key
        canon = _META_CANON.get(low)
        if canon is not None and canon != key:
            raise DVRInputError(
                f"{path}: field {key!r}: MetaImage keys are case-sensitive; expected {canon!r}"
            )
        if key in _META_ARRAYS and "NDims" not in fields:
            raise DVRInputError(f"{path}: field {key!r}: comes before 'NDims'")
        fields[key] = value
    for group in _META_SYNONYMS:
        given = [k for k in group if k in fields]
        if len(given) > 1:
            raise DVRInputError(
                f"{path}: fields {' and '.join(map(repr, given))}: synonyms given together; "
                "give one"
            )
    return fields, min(pos, len(head))


def meta_layout(path: Path, *, limit: int | None = None, hint: str | None = None) -> Layout:
    """Parse a ``.mha``/``.mhd`` header into a :class:`Layout` (sizes checked, nothing read)."""
    fields, header_end = meta_fields(path)

    def need(key: str) -> str:
        if key not in fields:
            raise DVRInputError(f"{path}: MetaImage header has no {key!r} field")
        return fields[key]

    if parse_int(need("NDims"), path, "NDims") != 3:
        raise DVRInputError(f"{path}: field 'NDims': expected 3, got {shown(fields['NDims'])}")
    dims = tuple(_ints(need("DimSize"), 3, path, "DimSize"))
    etype = need("ElementType")
    if etype not in META_TYPES:
        raise DVRInputError(
            f"{path}: field 'ElementType': unsupported type {shown(etype)}; expected one of "
            f"{', '.join(META_TYPES)}"
        )
    channels = parse_int(fields.get("ElementNumberOfChannels", "1"), path,
                         "ElementNumberOfChannels")  # fmt: skip
    if channels != 1:
        raise DVRInputError(
            f"{path}: field 'ElementNumberOfChannels': {channels} channels; expected a scalar "
            "(1-channel) image"
        )
    if not _bool(fields.get("BinaryData", "True"), path, "BinaryData"):
        raise DVRInputError(f"{path}: field 'BinaryData': ASCII voxel data is not supported")
    order_key = next((k for k in _META_SYNONYMS[2] if k in fields), None)
    msb = _bool(fields[order_key], path, order_key) if order_key else False
    dtype = np.dtype(META_TYPES[etype]).newbyteorder(">" if msb else "<")
    spacing = np.ones(3)
    if "ElementSpacing" in fields:
        spacing = np.array(_floats(fields["ElementSpacing"], 3, path, "ElementSpacing"))
    if "ElementSize" in fields:
        size = np.array(_floats(fields["ElementSize"], 3, path, "ElementSize"))
        if "ElementSpacing" in fields and not np.array_equal(size, spacing):
            raise DVRInputError(
                f"{path}: fields 'ElementSpacing' and 'ElementSize' disagree; give one"
            )
        spacing = size
    check_spacing(spacing, path, "ElementSpacing")
    key = next((k for k in _META_SYNONYMS[0] if k in fields), None)
    origin = np.array(_floats(fields[key], 3, path, key)) if key else np.zeros(3)
    key = next((k for k in _META_SYNONYMS[1] if k in fields), None)
    oriented = key is not None
    directions = np.eye(3)
    if key is not None:
        directions = np.array(_floats(fields[key], 9, path, "TransformMatrix")).reshape(3, 3).T
    expected = check_budget(path, dims, dtype, "DimSize", limit=limit, hint=hint)
    compressed = _bool(fields.get("CompressedData", "False"), path, "CompressedData")
    header_size = parse_int(fields.get("HeaderSize", "0"), path, "HeaderSize", lo=-1,
                            hi=2**62)  # fmt: skip
    data_file = need("ElementDataFile")
    if data_file in ("LOCAL", "Local", "local"):
        src = path
        if header_size > 0:
            raise DVRInputError(
                f"{path}: field 'HeaderSize': {header_size} with attached (LOCAL) data; the "
                "data starts after the header"
            )
        offset = header_end
    else:
        if data_file.split()[:1] == ["LIST"] or "%" in data_file:
            raise DVRInputError(f"{path}: field 'ElementDataFile': file lists are not supported")
        src = resolve_data_file(path, data_file, "ElementDataFile")
        offset = max(header_size, 0)
    where = f"{path} (data file {src.name})" if src != path else str(path)
    size = src.stat().st_size
    if header_size == -1:
        if compressed:
            raise DVRInputError(f"{path}: field 'HeaderSize': -1 needs uncompressed data")
        offset = size - expected
        if offset < (header_end if src == path else 0):
            raise DVRInputError(
                f"{where}: truncated: expected {expected} bytes, found "
                f"{max(size - (header_end if src == path else 0), 0)} (DimSize {dims})"
            )
    count = math.prod(dims)
    if compressed:
        stored = size - offset
        if "CompressedDataSize" in fields:
            claimed = parse_int(fields["CompressedDataSize"], path, "CompressedDataSize",
                                hi=2**62)  # fmt: skip
            if claimed > stored:
                raise DVRInputError(
                    f"{where}: truncated: field 'CompressedDataSize' claims {claimed} bytes, "
                    f"the file holds {max(stored, 0)}"
                )
            stored = claimed
        check_ratio(where, max(stored, 0), expected)

        def reader() -> np.ndarray:
            blob = _read_exact(src, offset, stored, where)
            return np.frombuffer(_inflate(blob, expected, where), dtype).copy()

    else:
        if size - offset < expected:
            raise DVRInputError(
                f"{where}: truncated: expected {expected} bytes, found {max(size - offset, 0)} "
                f"(DimSize {dims})"
            )

        def reader() -> np.ndarray:
            return _raw_array(src, offset, dtype, count, where)

    return Layout(path, dims, dtype, expected, directions * spacing, origin, oriented, src,
                  reader)  # fmt: skip


# -- legacy VTK structured points ------------------------------------------------------------

#: The legacy format's scalar types (its binary data is big-endian).
LEGACY_TYPES = {
    "char": "i1", "signed_char": "i1", "unsigned_char": "u1", "short": "i2",
    "unsigned_short": "u2", "int": "i4",
    "unsigned_int": "u4", "long": "i8", "unsigned_long": "u8", "vtktypeint64": "i8",
    "vtktypeuint64": "u8", "float": "f4", "double": "f8",
}  # fmt: skip
#: Longest line VTK's legacy reader takes.
_LEGACY_LINE = 256


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


def legacy_layout(path: Path, *, limit: int | None = None, hint: str | None = None) -> Layout:
    r"""Parse a legacy ``.vtk`` structured-points header into a :class:`Layout`.

    Accepted: the version line, a title, ``ASCII`` or ``BINARY``, ``DATASET
    STRUCTURED_POINTS``, each of ``DIMENSIONS``, ``SPACING`` (or ``ASPECT_RATIO``) and
    ``ORIGIN`` at most once, ``POINT_DATA`` (the number of points), one ``SCALARS`` array of
    one component with its ``LOOKUP_TABLE`` line, the data, then only white space.

    Examples
    --------
    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "grid.vtk"
    >>> _ = p.write_text("# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\n")
    >>> legacy_layout(p)
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: ...: field 'DATASET': holds 'POLYDATA'; expected ...
    """
    with open(path, "rb") as f:
        head = f.read(HEADER_MAX + 1)
    pos = 0

    def next_line(what: str) -> str:
        nonlocal pos
        while True:
            nl = head.find(b"\n", pos)
            if nl < 0:
                if len(head) > HEADER_MAX:
                    raise DVRInputError(f"{path}: the legacy VTK header is longer than "
                                        f"{HEADER_MAX} bytes")  # fmt: skip
                raise DVRInputError(f"{path}: truncated header: no {what} line")
            raw, pos = head[pos:nl], nl + 1
            if len(raw) > _LEGACY_LINE:
                raise DVRInputError(
                    f"{path}: header line {shown(raw.decode('latin-1'))} is longer than "
                    f"{_LEGACY_LINE} characters"
                )
            line = raw.decode("latin-1").strip()
            if line or what in ("title",):
                return line

    if not next_line("version").startswith("# vtk DataFile"):
        raise DVRInputError(f"{path}: not a legacy VTK file (no '# vtk DataFile' first line)")
    next_line("title")
    mode = next_line("ASCII/BINARY").upper()
    if mode not in ("ASCII", "BINARY"):
        raise DVRInputError(f"{path}: field 'format': expected ASCII or BINARY, got {shown(mode)}")
    words = next_line("DATASET").split()
    if not words or words[0].upper() != "DATASET":
        raise DVRInputError(f"{path}: field 'DATASET': expected 'DATASET STRUCTURED_POINTS'")
    kind = " ".join(words[1:]).upper()
    if kind != "STRUCTURED_POINTS":
        raise DVRInputError(
            f"{path}: field 'DATASET': holds {shown(kind or 'nothing')}; expected "
            "STRUCTURED_POINTS (image data)"
        )
    fields: dict[str, list[str]] = {}
    while True:
        words = next_line("POINT_DATA").split()
        key = words[0].upper()
        if key == "POINT_DATA":
            break
        if key not in ("DIMENSIONS", "SPACING", "ASPECT_RATIO", "ORIGIN"):
            raise DVRInputError(
                f"{path}: field {words[0]!r}: not taken in structured points (expected "
                "DIMENSIONS, SPACING, ORIGIN, then POINT_DATA)"
            )
        name = "SPACING" if key == "ASPECT_RATIO" else key
        if name in fields:
            raise DVRInputError(f"{path}: field {key!r}: given twice; give each field once")
        fields[name] = words[1:]
    if "DIMENSIONS" not in fields:
        raise DVRInputError(f"{path}: field 'DIMENSIONS': missing")
    dims = tuple(_ints(" ".join(fields["DIMENSIONS"]), 3, path, "DIMENSIONS"))
    spacing = _floats(" ".join(fields.get("SPACING", ["1", "1", "1"])), 3, path, "SPACING")
    check_spacing(spacing, path, "SPACING")
    origin = _floats(" ".join(fields.get("ORIGIN", ["0", "0", "0"])), 3, path, "ORIGIN")
    count = math.prod(dims)
    if len(words) != 2 or parse_int(words[1], path, "POINT_DATA", lo=0, hi=2**62) != count:
        raise DVRInputError(
            f"{path}: field 'POINT_DATA': expected the number of points {count} (DIMENSIONS "
            f"{' '.join(map(str, dims))}), got {shown(' '.join(words[1:]))}"
        )
    words = next_line("SCALARS").split()
    key = words[0].upper()
    if key == "COLOR_SCALARS" and len(words) == 3:
        # VTK writes unsigned char scalars so: binary bytes, no lookup table
        if mode != "BINARY":
            raise DVRInputError(
                f"{path}: field 'COLOR_SCALARS': ASCII colour scalars are not supported"
            )
        kind, ncomp = "unsigned_char", words[2]
    elif key == "SCALARS" and len(words) in (3, 4):
        kind, ncomp = words[2].lower(), (words[3] if len(words) == 4 else "1")
        if kind not in LEGACY_TYPES:
            raise DVRInputError(
                f"{path}: field 'SCALARS': unsupported type {shown(words[2])}; expected one "
                f"of {', '.join(LEGACY_TYPES)}"
            )
    else:
        raise DVRInputError(
            f"{path}: field {words[0]!r}: expected 'SCALARS name type' (one scalar array)"
        )
    if parse_int(ncomp, path, key) != 1:
        raise DVRInputError(
            f"{path}: field {key!r}: point array {words[1]!r} has {ncomp} components; "
            "expected a scalar (1-component) array"
        )
    if key == "SCALARS":
        words = next_line("LOOKUP_TABLE").split()
        if words[0].upper() != "LOOKUP_TABLE" or len(words) != 2:
            raise DVRInputError(f"{path}: field {words[0]!r}: expected 'LOOKUP_TABLE name'")
    dtype = np.dtype(LEGACY_TYPES[kind]).newbyteorder(">")
    nbytes = check_budget(path, dims, dtype, "DIMENSIONS", limit=limit, hint=hint)
    start = pos
    size = path.stat().st_size
    if mode == "BINARY":
        if size - start < nbytes:
            raise DVRInputError(
                f"{path}: truncated: expected {nbytes} bytes of voxel data, found "
                f"{size - start} (DIMENSIONS {dims})"
            )

        def reader() -> np.ndarray:
            out = _raw_array(path, start, dtype, count, path)
            with open(path, "rb") as f:
                f.seek(start + nbytes)
                rest = f.read(4097)
            if rest.strip() or len(rest) > 4096:
                raise DVRInputError(
                    f"{path}: unexpected content after the voxel data (a file holds one "
                    "scalar array)"
                )
            return out

    else:
        from dvr_perception.rays import memory

        cap = memory.limit() if limit is None else int(limit)
        if size - start > min(26 * count, 2 * cap) + 4096:  # 26: a float64 in full, a space
            raise DVRInputError(
                f"{path}: the ASCII data ({size - start} bytes) is far longer than {count} numbers"
            )

        def reader() -> np.ndarray:
            with open(path, "rb") as f:
                f.seek(start)
                text = f.read().decode("latin-1")
            return _ascii_values(text, dtype, count, path, "SCALARS")

    axes = np.diag(spacing)
    return Layout(path, dims, dtype, nbytes, axes, np.array(origin), False, path, reader)


# -- VTK XML image data ----------------------------------------------------------------------

#: VTK's XML type names.
XML_TYPES = {
    "Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4", "UInt32": "u4",
    "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8",
}  # fmt: skip
_HEADER_TYPES = {"UInt32": "u4", "UInt64": "u8"}
_COMPRESSORS = ("", "vtkZLibDataCompressor")


def _xml_part(path: Path, limit: int) -> tuple[bytes, int | None, str | None]:
    """Return a ``.vti`` file's XML, the appended data's first byte and its encoding.

    The XML is closed right after the ``<AppendedData>`` start tag; without appended data the
    whole file is the XML and the other two are ``None``.
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(HEADER_MAX)
    at = head.find(b"<AppendedData")
    if at < 0:
        if size > HEADER_MAX:  # inline data: the whole file is XML
            if size > 2 * limit + HEADER_MAX:
                raise DVRInputError(
                    f"{path}: no <AppendedData> in its first {HEADER_MAX} bytes and the file "
                    f"holds {size} bytes, more than inline data within the memory limit"
                )
            head = path.read_bytes()
            if b"<AppendedData" in head:
                raise DVRInputError(f"{path}: the XML header is longer than {HEADER_MAX} bytes")
        _plain_xml(path, head)
        return head, None, None
    xml = head[:at]
    _plain_xml(path, xml)
    # the end of the start tag: the first '>' outside quotes
    quote, end = None, None
    for i in range(at, len(head)):
        c = head[i : i + 1]
        if quote:
            if c == quote:
                quote = None
        elif c in (b'"', b"'"):
            quote = c
        elif c == b">":
            end = i + 1
            break
    if end is None:
        raise DVRInputError(f"{path}: unterminated <AppendedData> element")
    tag = head[at:end]
    if tag.endswith(b"/>"):
        raise DVRInputError(f"{path}: empty <AppendedData/> element")
    under = head.find(b"_", end)
    if under < 0 or head[end:under].strip():
        raise DVRInputError(
            f"{path}: field 'AppendedData': expected white space and '_' before the data"
        )
    m = re.search(rb"""\bencoding\s*=\s*(["'])(.*?)\1""", tag)
    encoding = m.group(2).decode("latin-1") if m else None
    return xml + tag + b"</AppendedData></VTKFile>", under + 1, encoding


def _plain_xml(path: Path, xml: bytes) -> None:
    """Refuse comments, processing instructions, DOCTYPE and CDATA (the XML declaration aside)."""
    body = xml.lstrip()
    if body.startswith(b"<?xml"):
        close = body.find(b"?>")
        body = body[close + 2 :] if close >= 0 else body
    for mark, what in ((b"<!--", "an XML comment"), (b"<!", "a DOCTYPE or CDATA section"),
                       (b"<?", "a processing instruction")):  # fmt: skip
        if mark in body:
            raise DVRInputError(
                f"{path}: holds {what}; a .vti header must be plain elements (refused, as it "
                "could be read two ways)"
            )


@dataclass
class _Array:
    name: str
    dtype: np.dtype
    comps: int
    tuples: int
    fmt: str
    offset: int
    element: ET.Element
    where: str


def _xml_attr(elem: ET.Element, name: str, where, default: str | None = None) -> str:
    value = elem.get(name, default)
    if value is None:
        raise DVRInputError(f"{where}: field {name!r}: missing in <{elem.tag}>")
    return value


def _vti_array(elem: ET.Element, where: str, tuples: int, order: str) -> _Array:
    if elem.tag != "DataArray":
        raise DVRInputError(f"{where}: element <{elem.tag}>: expected <DataArray>")
    kind = elem.get("type", "")
    if kind not in XML_TYPES:
        raise DVRInputError(
            f"{where}: field 'DataArray type': unsupported type {shown(kind)}; expected one of "
            f"{', '.join(XML_TYPES)}"
        )
    comps = parse_int(elem.get("NumberOfComponents", "1"), where, "NumberOfComponents",
                      hi=4096)  # fmt: skip
    fmt = elem.get("format", "")
    if fmt not in ("ascii", "binary", "appended"):
        raise DVRInputError(
            f"{where}: field 'format': {shown(fmt)}; expected ascii, binary or appended"
        )
    offset = 0
    if fmt == "appended":
        offset = parse_int(_xml_attr(elem, "offset", where), where, "offset", lo=0, hi=2**62)
    if "NumberOfTuples" in elem.attrib:
        n = parse_int(elem.get("NumberOfTuples"), where, "NumberOfTuples", lo=0, hi=2**62)
        if n != tuples:
            raise DVRInputError(f"{where}: field 'NumberOfTuples': {n}, the extent holds {tuples}")
    dtype = np.dtype(XML_TYPES[kind]).newbyteorder(order)
    name = elem.get("Name", "")
    return _Array(name, dtype, comps, tuples, fmt, offset, elem, where)


def vti_layout(path: Path, *, limit: int | None = None, hint: str | None = None) -> Layout:
    """Parse a ``.vti`` file's XML into a :class:`Layout` (every array sized, nothing read).

    Examples
    --------
    >>> import os, tempfile
    >>> p = Path(tempfile.mkdtemp()) / "huge.vti"
    >>> _ = p.write_text('<VTKFile type="ImageData"><ImageData WholeExtent="0 99999 0 99999 '
    ...                  '0 99999" Spacing="1 1 1"><Piece Extent="0 99999 0 99999 0 99999">'
    ...                  '<PointData><DataArray type="Float64" Name="s" format="ascii"/>'
    ...                  '</PointData></Piece></ImageData></VTKFile>')
    >>> vti_layout(p)
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: ...field 'WholeExtent': sizes 100000 100000 100000 ...
    """
    from dvr_perception.rays import memory

    cap = memory.limit() if limit is None else int(limit)
    xml, data_start, encoding = _xml_part(path, cap)
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as exc:
        raise DVRInputError(f"{path}: malformed VTK XML ({exc})") from None
    if root.tag != "VTKFile" or root.get("type") != "ImageData":
        raise DVRInputError(
            f'{path}: expected a <VTKFile type="ImageData"> root element, got <{root.tag}>'
        )
    order = {"LittleEndian": "<", "BigEndian": ">"}.get(root.get("byte_order", "LittleEndian"))
    if order is None:
        raise DVRInputError(f"{path}: field 'byte_order': {shown(root.get('byte_order'))}")
    htype = root.get("header_type", "UInt32")
    if htype not in _HEADER_TYPES:
        raise DVRInputError(f"{path}: field 'header_type': {shown(htype)}; expected UInt32/UInt64")
    header = np.dtype(_HEADER_TYPES[htype]).newbyteorder(order)
    compressor = root.get("compressor", "")
    if compressor not in _COMPRESSORS:
        raise DVRInputError(
            f"{path}: field 'compressor': {shown(compressor)} is not supported; save it "
            "uncompressed or with vtkZLibDataCompressor"
        )
    images = [c for c in root if c.tag == "ImageData"]
    others = [c.tag for c in root if c.tag not in ("ImageData", "AppendedData")]
    if len(images) != 1 or others:
        raise DVRInputError(
            f"{path}: expected one <ImageData> (and <AppendedData>) in <VTKFile>, got "
            f"{[c.tag for c in root]}"
        )
    image = images[0]
    where = str(path)
    extent = _ints(_xml_attr(image, "WholeExtent", where), 6, where, "WholeExtent",
                   lo=-(2**31))  # fmt: skip
    dims = [extent[2 * i + 1] - extent[2 * i] + 1 for i in range(3)]
    if min(dims) < 1:
        raise DVRInputError(f"{path}: field 'WholeExtent': empty extent {extent}")
    for i in range(3):
        parse_int(str(dims[i]), path, "WholeExtent")  # at most 2**31 - 1 points
    spacing = check_spacing(_floats(image.get("Spacing", "1 1 1"), 3, path, "Spacing"), path,
                            "Spacing")  # fmt: skip
    origin = np.array(_floats(image.get("Origin", "0 0 0"), 3, path, "Origin"))
    oriented = "Direction" in image.attrib
    direction = np.eye(3)
    if oriented:
        direction = np.array(_floats(image.get("Direction"), 9, path, "Direction")).reshape(3, 3)
    tags = [c.tag for c in image]
    if tags not in (["Piece"], ["FieldData", "Piece"]):
        raise DVRInputError(
            f"{path}: expected one <Piece> (after an optional <FieldData>) in <ImageData>, got "
            f"{tags}"
        )
    piece = image[len(tags) - 1]
    field_arrays = []
    if tags[0] == "FieldData":  # e.g. ParaView's TimeValue: sized by NumberOfTuples
        for elem in image[0]:
            n = parse_int(_xml_attr(elem, "NumberOfTuples", where), where, "NumberOfTuples",
                          lo=0, hi=2**40)  # fmt: skip
            field_arrays.append(_vti_array(elem, f"{path}: FieldData", n, order))
    if _ints(_xml_attr(piece, "Extent", where), 6, where, "Extent", lo=-(2**31)) != extent:
        raise DVRInputError(f"{path}: field 'Extent': the piece differs from the WholeExtent")
    points = math.prod(dims)
    cells = math.prod(max(d - 1, 1) for d in dims)
    arrays: dict[str, list[_Array]] = {"PointData": [], "CellData": []}
    active = None
    seen_parts: set[str] = set()
    for part in piece:
        if part.tag not in arrays:
            raise DVRInputError(f"{path}: element <{part.tag}>: expected <PointData>/<CellData>")
        if part.tag in seen_parts:
            raise DVRInputError(f"{path}: element <{part.tag}>: given twice in the <Piece>")
        seen_parts.add(part.tag)
        n = points if part.tag == "PointData" else cells
        for elem in part:
            arrays[part.tag].append(_vti_array(elem, f"{path}: {part.tag}", n, order))
        if part.tag == "PointData":
            active = part.get("Scalars")
    every = arrays["PointData"] + arrays["CellData"] + field_arrays
    total = sum(a.tuples * a.comps * a.dtype.itemsize for a in every)
    widest = max((a.dtype for a in every), key=lambda d: d.itemsize, default=np.dtype("u1"))
    # every array VTK would allocate counts, not only the one read
    check_budget(path, dims, widest, "WholeExtent", limit=limit, hint=hint, nbytes=total,
                 what=f"({len(every)} arrays)" if len(every) > 1 else None)  # fmt: skip
    if any(a.fmt == "appended" for a in every) and data_start is None:
        raise DVRInputError(f"{path}: field 'format': appended arrays but no <AppendedData>")
    if data_start is not None and encoding not in ("raw", "base64"):
        raise DVRInputError(
            f"{path}: field 'AppendedData encoding': {shown(encoding or '(none)')}; expected raw "
            "or base64"
        )
    chosen = _choose(path, arrays["PointData"], active, bool(arrays["CellData"]))
    if chosen.comps != 1:
        raise DVRInputError(
            f"{path}: point array {chosen.name or 'scalars'!r} has {chosen.comps} components; "
            "expected a scalar (1-component) array"
        )
    expected = points * chosen.dtype.itemsize
    source = _VtiSource(path, header, bool(compressor), data_start, encoding)
    ends = [0]
    for arr in every:  # sizes and bounds of every array, before anything is decoded
        ends.append(source.check(arr, arr.tuples * arr.comps * arr.dtype.itemsize))
    source.check_end(max(ends))

    def reader() -> np.ndarray:
        blob = source.read(chosen, expected)
        if isinstance(blob, bytes):
            return np.frombuffer(blob, chosen.dtype).copy()
        return blob.view(chosen.dtype) if blob.dtype == np.uint8 else blob

    axes = direction * np.asarray(spacing)
    origin = origin + axes @ np.array(extent[::2], float)  # the first point of the extent
    return Layout(path, (dims[0], dims[1], dims[2]), chosen.dtype, total, axes, origin, oriented,
                  path, reader)  # fmt: skip


def _choose(path: Path, point: list[_Array], active: str | None, cells: bool) -> _Array:
    """Return the point array VTK would make the scalars (as :func:`.convert.from_vtk_image`)."""
    for arr in point:
        if active is not None and arr.name == active:
            return arr
    if len(point) == 1:  # no (or no such) active scalars: the only array
        return point[0]
    if not point and cells:
        raise DVRInputError(
            f"{path}: the image holds only cell data; expected point scalars (convert with a "
            "cell-to-point filter first)"
        )
    n = len(point)
    raise DVRInputError(
        f"{path}: no point scalars" + (f" among {n} point arrays; pass array=NAME" if n else "")
    )


class _VtiSource:
    """Locates and decodes one DataArray's bytes (inline or appended, raw or base64, zlib)."""

    def __init__(self, path: Path, header: np.dtype, compressed: bool, start, encoding) -> None:
        self.path = path
        self.header = header
        self.hs = header.itemsize
        self.compressed = compressed
        self.start = start
        self.encoding = encoding
        self.size = path.stat().st_size
        if start is not None:  # the appended data ends where </AppendedData> starts
            first = max(start, self.size - HEADER_MAX)
            with open(path, "rb") as f:
                f.seek(first)
                at = f.read().rfind(b"</AppendedData>")
            if at < 0:
                raise DVRInputError(
                    f"{path}: truncated: no closing </AppendedData> at the end of the file"
                )
            self.size = first + at

    # the appended section: raw bytes or base64 text, from `start + offset`
    def _appended(self, offset: int, count: int, what: str) -> bytes:
        at = self.start + offset
        if self.size - at < count:
            raise DVRInputError(
                f"{self.path}: {what}: truncated: expected {count} bytes from appended offset "
                f"{offset}, found {max(self.size - at, 0)}"
            )
        return _read_exact(self.path, at, count, f"{self.path}: {what}")

    def _words(self, blob: bytes, n: int) -> list[int]:
        return [int(v) for v in np.frombuffer(blob[: n * self.hs], self.header)]

    def _b64(self, text: bytes, what: str) -> bytes:
        try:
            return base64.b64decode(text, validate=True)
        except (binascii.Error, ValueError):
            raise DVRInputError(
                f"{self.path}: {what}: truncated or malformed base64 data"
            ) from None

    def _block_sizes(self, words: list[int], expected: int, what: str) -> list[int]:
        nblocks, block, last = words[0], words[1], words[2]
        if nblocks == 0:
            sizes = []
        else:
            if block <= 0 or not 0 <= last <= block:
                raise DVRInputError(f"{self.path}: {what}: bad compression header {words[:3]}")
            sizes = [block] * (nblocks - 1) + [last or block]
        if sum(sizes) != expected:
            raise DVRInputError(
                f"{self.path}: {what}: the compressed blocks hold {sum(sizes)} bytes, the "
                f"extent needs {expected} (truncated or wrong sizes)"
            )
        return sizes

    def check_end(self, end: int) -> None:
        """Refuse appended data that does not end where ``</AppendedData>`` follows.

        After the last array only a line break (and indentation) may come, as VTK writes it: a
        file cut short would otherwise have its closing tag read as data.
        """
        if self.start is None:
            return
        with open(self.path, "rb") as f:
            f.seek(self.start + end)
            gap = f.read(max(self.size - self.start - end, 0))
        if gap and (gap[:1] not in (b"\n", b"\r") or gap.strip()):
            raise DVRInputError(
                f"{self.path}: truncated or malformed appended data: the arrays end "
                f"{len(gap)} bytes before </AppendedData>, at {gap[:12]!r}"
            )

    def check(self, arr: _Array, expected: int) -> int:
        """Refuse an array whose stored size cannot be what the header claims.

        Returns where the array's appended data ends (0 for inline arrays).
        """
        what = f"array {arr.name!r}"
        if arr.fmt == "ascii":
            return 0
        if arr.fmt == "binary":
            text = (arr.element.text or "").encode("latin-1")
            if len(text) > 2 * expected + 4096 and not self.compressed:
                raise DVRInputError(f"{self.path}: {what}: more data than its extent holds")
            return 0
        if self.start + arr.offset > self.size:
            raise DVRInputError(f"{self.path}: {what}: truncated: its offset lies past the end")
        raw = self.encoding == "raw" and not self.compressed
        if raw and self.size - self.start - arr.offset < self.hs + expected:
            raise DVRInputError(
                f"{self.path}: {what}: truncated: expected {expected} bytes of data, found "
                f"{max(self.size - self.start - arr.offset - self.hs, 0)}"
            )
        b64 = self.encoding == "base64"
        if not self.compressed:
            n = self.hs + expected
            return arr.offset + (4 * (-(-n // 3)) if b64 else n)
        if b64:
            first = self._b64(self._appended(arr.offset, 4 * self.hs, what), what)
            nblocks = self._nblocks(self._words(first, 3)[0], expected, what)
            hlen = 4 * (-(-((3 + nblocks) * self.hs) // 3))
            words = self._words(self._b64(self._appended(arr.offset, hlen, what), what),
                                3 + nblocks)  # fmt: skip
            return arr.offset + hlen + 4 * (-(-sum(words[3:]) // 3))
        words = self._words(self._appended(arr.offset, 3 * self.hs, what), 3)
        nblocks = self._nblocks(words[0], expected, what)
        hlen = (3 + nblocks) * self.hs
        words = self._words(self._appended(arr.offset, hlen, what), 3 + nblocks)
        return arr.offset + hlen + sum(words[3:])

    def read(self, arr: _Array, expected: int):
        """Return the decoded (decompressed) bytes of ``arr``: exactly ``expected``."""
        what = f"array {arr.name!r}"
        if arr.fmt == "ascii":
            return _ascii_values(arr.element.text or "", arr.dtype, arr.tuples * arr.comps,
                                 self.path, what)  # fmt: skip
        if arr.fmt == "binary":
            text = re.sub(rb"\s+", b"", (arr.element.text or "").encode("latin-1"))
            return self._decode64(lambda a, n: text[a : a + n], expected, what)
        if self.encoding == "base64":

            def chars(at: int, n: int) -> bytes:
                first = self.start + arr.offset + at
                with open(self.path, "rb") as f:
                    f.seek(first)
                    return f.read(max(min(n, self.size - first), 0))

            return self._decode64(chars, expected, what)
        # raw appended
        if not self.compressed:
            (n,) = self._words(self._appended(arr.offset, self.hs, what), 1)
            if n != expected:
                raise DVRInputError(
                    f"{self.path}: {what}: holds {n} bytes, the extent needs {expected}"
                )
            at = self.start + arr.offset + self.hs
            if self.size - at < expected:
                raise DVRInputError(
                    f"{self.path}: {what}: truncated: expected {expected} bytes, found "
                    f"{max(self.size - at, 0)}"
                )
            return _raw_array(self.path, at, np.dtype(np.uint8), expected, f"{self.path}: {what}")
        words = self._words(self._appended(arr.offset, 3 * self.hs, what), 3)
        nblocks = self._nblocks(words[0], expected, what)
        words = self._words(self._appended(arr.offset, (3 + nblocks) * self.hs, what),
                            3 + nblocks)  # fmt: skip
        sizes = self._block_sizes(words, expected, what)
        packed = self._appended(arr.offset + (3 + nblocks) * self.hs, sum(words[3:]), what)
        return self._unpack(packed, words[3:], sizes, what)

    def _nblocks(self, nblocks: int, expected: int, what: str) -> int:
        if nblocks > expected + 1:  # each block holds at least one byte
            raise DVRInputError(f"{self.path}: {what}: {nblocks} blocks for {expected} bytes")
        return nblocks

    def _decode64(self, chars, expected: int, what: str) -> bytes:
        """Decode base64 text read by ``chars(start, count)`` (VTK's header layout)."""
        if not self.compressed:  # the size word and the data, encoded together
            n = 4 * (-(-(self.hs + expected) // 3))
            blob = self._b64(chars(0, n), what)
            if len(blob) < self.hs:
                raise DVRInputError(f"{self.path}: {what}: truncated: no size header")
            (stored,) = self._words(blob, 1)
            if stored != expected or len(blob) - self.hs < expected:
                raise DVRInputError(
                    f"{self.path}: {what}: truncated or wrong size: holds "
                    f"{min(stored, len(blob) - self.hs)} bytes, the extent needs {expected}"
                )
            return blob[self.hs : self.hs + expected]
        # compressed: the header words, then the compressed blocks, each encoded on its own
        first = self._b64(chars(0, 4 * self.hs), what)  # 3 words: exactly 4 * hs characters
        if len(first) < 3 * self.hs:
            raise DVRInputError(f"{self.path}: {what}: truncated compression header")
        nblocks = self._nblocks(self._words(first, 3)[0], expected, what)
        hlen = 4 * (-(-((3 + nblocks) * self.hs) // 3))
        head = self._b64(chars(0, hlen), what)
        if len(head) < (3 + nblocks) * self.hs:
            raise DVRInputError(f"{self.path}: {what}: truncated compression header")
        words = self._words(head, 3 + nblocks)
        sizes = self._block_sizes(words, expected, what)
        packed = self._b64(chars(hlen, 4 * (-(-sum(words[3:]) // 3))), what)
        return self._unpack(packed, words[3:], sizes, what)

    def _unpack(self, packed: bytes, stored: list[int], sizes: list[int], what: str):
        if len(packed) < sum(stored):
            raise DVRInputError(
                f"{self.path}: {what}: truncated: {len(packed)} compressed bytes, the header "
                f"says {sum(stored)}"
            )
        out = np.empty(sum(sizes), np.uint8)  # every byte written below, or refused
        pos = done = 0
        for n, size in zip(stored, sizes, strict=True):
            out[done : done + size] = np.frombuffer(
                _inflate(packed[pos : pos + n], size, f"{self.path}: {what}"), np.uint8
            )
            pos += n
            done += size
        return out


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
