"""VTK XML image data (``.vti``): a real XML parse of the header, then our own read.

Part of the one-parse header checks: see :mod:`dvr_perception.volume._headers`.
"""

from __future__ import annotations

import base64
import binascii
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._layout import (
    Layout,
    _ascii_values,
    _floats,
    _inflate,
    _ints,
    _raw_array,
    _read_exact,
)
from dvr_perception.volume._limits import (
    HEADER_MAX,
    check_budget,
    check_spacing,
    parse_int,
    shown,
)

__all__ = ["XML_TYPES", "vti_layout"]

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
    from dvr_perception import _memory as memory

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
