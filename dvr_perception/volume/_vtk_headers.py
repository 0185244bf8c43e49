"""Header checks of the VTK-read formats: XML image data (``.vti``) and legacy ``.vtk``.

VTK allocates what a header claims before it reads a byte of data, so a 200-byte file
claiming 10⁴ × 10⁴ × 10⁴ voxels makes it reserve terabytes (or crash).  These checks read
at most :data:`HEAD_MAX` bytes of the header, parse its sizes, spacing and scalar type with
the limits of :mod:`._limits` (short number tokens, exact products, the memory budget) and
refuse a bad header with one :class:`~dvr_perception.errors.DVRInputError` naming the file
and the field, before VTK opens the file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._limits import check_budget, check_spacing, parse_float, parse_int, shown

__all__ = ["HEAD_MAX", "check_legacy_vtk", "check_vti"]

#: Bytes of a file read to find its header.
HEAD_MAX = 1 << 16
#: Item sizes of VTK's XML ``type`` names.
_XML_TYPES = {
    "Int8": 1, "UInt8": 1, "Int16": 2, "UInt16": 2, "Int32": 4, "UInt32": 4, "Int64": 8,
    "UInt64": 8, "Float32": 4, "Float64": 8,
}  # fmt: skip
#: Item sizes of the legacy format's scalar type names.
_LEGACY_TYPES = {
    "bit": 1, "char": 1, "unsigned_char": 1, "short": 2, "unsigned_short": 2, "int": 4,
    "unsigned_int": 4, "long": 8, "unsigned_long": 8, "vtktypeint64": 8, "vtktypeuint64": 8,
    "float": 4, "double": 8,
}  # fmt: skip


def _head(path: Path) -> str:
    with open(path, "rb") as f:
        return f.read(HEAD_MAX).decode("latin-1")


def _attribute(tag: str, name: str) -> str | None:
    m = re.search(rf'\b{name}\s*=\s*"([^"]*)"', tag)
    return m.group(1) if m else None


def check_vti(path: Path) -> bool:
    """Check a ``.vti`` file's ``<ImageData>`` extent, spacing and scalar type.

    Returns whether the element records a ``Direction`` (VTK >= 9.1 writes one); without it
    the file records no patient orientation.

    Examples
    --------
    >>> import os, tempfile
    >>> p = Path(tempfile.mkdtemp()) / "huge.vti"
    >>> _ = p.write_text('<VTKFile type="ImageData"><ImageData WholeExtent="0 99999 0 99999 '
    ...                  '0 99999" Spacing="1 1 1"><Piece><PointData><DataArray '
    ...                  'type="Float64" Name="s"/></PointData></Piece></ImageData></VTKFile>')
    >>> check_vti(p)
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: ...field 'WholeExtent': sizes 100000 100000 100000 ...
    """
    head = _head(path)
    m = re.search(r"<ImageData\b[^>]*>", head)
    if m is None:
        raise DVRInputError(
            f"{path}: no <ImageData ...> element in its first {HEAD_MAX} bytes; expected a VTK "
            "XML image data file"
        )
    tag = m.group(0)
    extent = _attribute(tag, "WholeExtent")
    if extent is None or len(extent.split()) != 6:
        raise DVRInputError(
            f"{path}: field 'WholeExtent': expected 6 integers, got {shown(extent or '')}"
        )
    lo_hi = [parse_int(t, path, "WholeExtent", lo=-(2**31)) for t in extent.split()]
    dims = [lo_hi[2 * i + 1] - lo_hi[2 * i] + 1 for i in range(3)]
    if min(dims) < 1:
        raise DVRInputError(f"{path}: field 'WholeExtent': empty extent {shown(extent)}")
    spacing = _attribute(tag, "Spacing")
    if spacing is not None:
        vals = spacing.split()
        if len(vals) != 3:
            raise DVRInputError(f"{path}: field 'Spacing': expected 3 numbers, got {shown(vals)}")
        check_spacing([parse_float(v, path, "Spacing") for v in vals], path, "Spacing")
    for v in (_attribute(tag, "Origin") or "").split()[:3]:
        parse_float(v, path, "Origin")
    array = re.search(r"<DataArray\b[^>]*>", head[m.end() :])
    size, comps = 8, 1  # no array seen in the head: the widest type
    if array is not None:
        kind = _attribute(array.group(0), "type")
        if kind not in _XML_TYPES:
            raise DVRInputError(
                f"{path}: field 'DataArray type': unsupported type {shown(kind or '')}; "
                f"expected one of {', '.join(_XML_TYPES)}"
            )
        size = _XML_TYPES[kind]
        comps = parse_int(_attribute(array.group(0), "NumberOfComponents") or "1", path,
                          "NumberOfComponents")  # fmt: skip
    check_budget(path, (*dims, comps), np.dtype(f"u{size}"), "WholeExtent")
    return _attribute(tag, "Direction") is not None


def vti_axes(path: Path) -> np.ndarray:
    """Return a ``.vti`` file's axis vectors (columns: ``Direction`` times ``Spacing``).

    From the ``<ImageData>`` element only (no data read); identity directions when the file
    records no ``Direction``.
    """
    m = re.search(r"<ImageData\b[^>]*>", _head(path))
    if m is None:
        raise DVRInputError(f"{path}: no <ImageData ...> element; expected a VTK XML image file")
    fields = {}
    for name, n in (("Spacing", 3), ("Direction", 9)):
        text = _attribute(m.group(0), name)
        vals = text.split() if text is not None else []
        if text is not None and len(vals) != n:
            raise DVRInputError(f"{path}: field {name!r}: expected {n} numbers, got {shown(vals)}")
        fields[name] = [parse_float(v, path, name) for v in vals]
    spacing = np.array(fields["Spacing"] or [1.0, 1.0, 1.0])
    direction = np.array(fields["Direction"] or np.eye(3).ravel()).reshape(3, 3)
    return direction * spacing  # VTK's matrix is row-major, its columns are the index axes


def check_legacy_vtk(path: Path) -> None:
    r"""Check a legacy ``.vtk`` file: structured points, its sizes, spacing and scalar type.

    Examples
    --------
    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "grid.vtk"
    >>> _ = p.write_text("# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\n")
    >>> check_legacy_vtk(p)
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: ...: field 'DATASET': holds 'POLYDATA'; expected ...
    """
    lines = _head(path).split("\n")[:40]
    if not lines[0].startswith("# vtk DataFile"):
        raise DVRInputError(f"{path}: not a legacy VTK file (no '# vtk DataFile' first line)")
    words = [ln.split() for ln in lines[3:]]
    fields = {w[0].upper(): w[1:] for w in words if w}
    kind = " ".join(fields.get("DATASET", [])).upper()
    if kind != "STRUCTURED_POINTS":
        raise DVRInputError(
            f"{path}: field 'DATASET': holds {shown(kind or 'nothing')}; expected "
            "STRUCTURED_POINTS (image data)"
        )
    if len(fields.get("DIMENSIONS", [])) != 3:
        raise DVRInputError(
            f"{path}: field 'DIMENSIONS': expected 3 integers, got "
            f"{shown(fields.get('DIMENSIONS', []))}"
        )
    dims = [parse_int(t, path, "DIMENSIONS") for t in fields["DIMENSIONS"]]
    for key in ("SPACING", "ASPECT_RATIO"):
        if key in fields:
            vals = fields[key][:3]
            if len(vals) != 3:
                raise DVRInputError(f"{path}: field {key!r}: expected 3 numbers, got {shown(vals)}")
            check_spacing([parse_float(v, path, key) for v in vals], path, key)
    for v in fields.get("ORIGIN", [])[:3]:
        parse_float(v, path, "ORIGIN")
    scalars = fields.get("SCALARS", [])
    size, comps = 8, 1
    if len(scalars) >= 2:
        if scalars[1].lower() not in _LEGACY_TYPES:
            raise DVRInputError(
                f"{path}: field 'SCALARS': unsupported type {shown(scalars[1])}; expected one "
                f"of {', '.join(_LEGACY_TYPES)}"
            )
        size = _LEGACY_TYPES[scalars[1].lower()]
        if len(scalars) >= 3:
            comps = parse_int(scalars[2], path, "SCALARS")
    check_budget(path, (*dims, comps), np.dtype(f"u{size}"), "DIMENSIONS")
