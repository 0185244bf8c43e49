"""Legacy VTK structured points (``.vtk``): one strict parse, then our own read.

Part of the one-parse header checks: see :mod:`dvr_perception.volume._headers`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._layout import (
    Layout,
    _ascii_values,
    _floats,
    _ints,
    _raw_array,
)
from dvr_perception.volume._limits import (
    HEADER_MAX,
    check_budget,
    check_spacing,
    parse_int,
    shown,
)

__all__ = ["LEGACY_TYPES", "legacy_layout"]

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
        from dvr_perception import _memory as memory

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
