"""MetaImage (``.mha``/``.mhd``) headers: one strict parse, then our own read.

Part of the one-parse header checks: see :mod:`dvr_perception.volume._headers`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._layout import (
    Layout,
    _bool,
    _floats,
    _inflate,
    _ints,
    _raw_array,
    _read_exact,
)
from dvr_perception.volume._limits import (
    HEADER_MAX,
    check_budget,
    check_ratio,
    check_spacing,
    parse_int,
    resolve_data_file,
    shown,
)

__all__ = ["META_TYPES", "meta_fields", "meta_layout"]

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
