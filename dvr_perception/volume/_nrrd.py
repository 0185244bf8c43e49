"""NRRD files (``.nrrd``, data attached; ``.nhdr``, detached data file), read and written here.

Not with ``vtkNrrdReader``: VTK 9.x reads a first axis shorter than 10 samples as vector
components, whatever ``kinds`` says, which silently corrupts small volumes.  The header is
untrusted (:mod:`dvr_perception.volume._limits`): sizes, spacing, encoding and file size are
checked against each other and the memory limit before any data is read.
"""

from __future__ import annotations

import contextlib
import math
import re
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._limits import (
    HEADER_MAX,
    MAX_TOKEN,
    check_budget,
    check_size,
    check_spacing,
    parse_float,
    parse_int,
    read_compressed,
    resolve_data_file,
    shown,
)
from dvr_perception.volume.orient import ras_to_lps
from dvr_perception.volume.volume import Volume

__all__ = [
    "NRRD_NAMES",
    "NRRD_TYPES",
    "nrrd_axes",
    "nrrd_header",
    "nrrd_oriented",
    "nrrd_space",
    "nrrd_vector",
    "read_nrrd",
    "write_nrrd",
]

#: NRRD ``type`` names per numpy type code.
_NRRD_ALIASES = {
    "i1": ("signed char", "int8", "int8_t"),
    "u1": ("uchar", "unsigned char", "uint8", "uint8_t"),
    "i2": ("short", "short int", "signed short", "signed short int", "int16", "int16_t"),
    "u2": ("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"),
    "i4": ("int", "signed int", "int32", "int32_t"),
    "u4": ("uint", "unsigned int", "uint32", "uint32_t"),
    "i8": ("longlong", "long long", "long long int", "signed long long", "int64", "int64_t"),
    "u8": ("ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t"),
    "f4": ("float",),
    "f8": ("double",),
}
#: NRRD ``type`` name (any alias) -> numpy type code.
NRRD_TYPES = {alias: code for code, names in _NRRD_ALIASES.items() for alias in names}
#: Numpy type code -> the ``type`` name written.
NRRD_NAMES = {"i1": "int8", "u1": "uint8", "i2": "int16", "u2": "uint16", "i4": "int32"}
NRRD_NAMES |= {"u4": "uint32", "i8": "int64", "u8": "uint64", "f4": "float", "f8": "double"}
_NRRD_ENCODINGS = {"raw": "raw", "gzip": "gzip", "gz": "gzip", "bzip2": "bzip2", "bz2": "bzip2"}
#: NRRD ``space`` values read, as the patient space they name.
_NRRD_SPACES = {
    "left-posterior-superior": "lps",
    "lps": "lps",
    "right-anterior-superior": "ras",
    "ras": "ras",
    "left-anterior-superior": "las",
    "las": "las",
    "scanner-xyz": "lps",
    "3d-right-handed": "lps",
}


_DATA_KEYS = {"data file", "datafile"}


def nrrd_header(path: Path, keyvalues: dict[str, str] | None = None) -> tuple[dict[str, str], int]:
    """Return the NRRD header's fields (keys lower case) and the data offset.

    ``key:=value`` lines are skipped, or collected into ``keyvalues`` (keys as written, values
    decoded as UTF-8 where they are valid UTF-8) when a dict is given.
    """
    with open(path, "rb") as f:
        head = f.read(HEADER_MAX)
    if not head.startswith(b"NRRD000"):
        raise DVRInputError(f"{path}: not a NRRD file (missing the 'NRRD000X' magic line)")
    fields: dict[str, str] = {}
    offset = head.index(b"\n") + 1 if b"\n" in head else len(head)
    ended = False
    for raw in head[offset:].split(b"\n"):
        if offset + len(raw) >= len(head) and len(head) == HEADER_MAX:
            break  # the last, possibly cut, line of a full buffer
        offset += len(raw) + 1
        line = raw.decode("latin-1").rstrip("\r")
        if not line.strip():
            ended = True
            break  # blank line: end of an attached header
        if line.startswith("#"):
            continue
        if ":=" in line:
            if keyvalues is not None:
                key, _, value = line.partition(":=")
                with contextlib.suppress(UnicodeDecodeError):
                    value = value.encode("latin-1").decode("utf-8")
                keyvalues[key] = value
            continue
        key, sep, value = line.partition(": ")
        if not sep:
            raise DVRInputError(f"{path}: malformed NRRD header line {shown(line)}")
        low = key.strip().lower()
        if low in fields or (low in ("data file", "datafile") and fields.keys() & _DATA_KEYS):
            raise DVRInputError(
                f"{path}: NRRD field {key.strip()!r}: given twice; each field may appear once"
            )
        fields[low] = value.strip()
    if not ended and len(head) == HEADER_MAX:
        raise DVRInputError(
            f"{path}: the NRRD header is longer than {HEADER_MAX} bytes (no blank line ends it)"
        )
    return fields, min(offset, len(head))


def nrrd_vector(text: str, path: Path, field: str) -> tuple[float, ...]:
    """Parse a NRRD vector ``(a,b,c)`` of field ``field`` (numbers checked)."""
    return tuple(parse_float(v, path, field) for v in text.strip().strip("()").split(","))


def read_nrrd(
    path: Path, *, limit: int | None = None, hint: str | None = None, check_only: bool = False
):
    """Read a NRRD file: ``(data, axes, origin, oriented)``.

    With ``check_only`` the header, sizes (against ``limit``, default the memory limit) and
    data file are checked and ``(dims, dtype, data file)`` returned without reading data.
    """
    fields, offset = nrrd_header(path)

    def need(key: str) -> str:
        if key not in fields:
            raise DVRInputError(f"{path}: NRRD header has no {key!r} field")
        return fields[key]

    dtype = NRRD_TYPES.get(" ".join(need("type").lower().split()))
    if dtype is None:
        raise DVRInputError(
            f"{path}: NRRD field 'type': unsupported type {shown(fields['type'])}; expected an "
            "integer or float scalar type"
        )
    if need("dimension") != "3":
        raise DVRInputError(
            f"{path}: NRRD field 'dimension': expected 3, got {shown(fields['dimension'])}"
        )
    tokens = need("sizes").split()
    if len(tokens) != 3 or not all(t.isdigit() or len(t) > MAX_TOKEN for t in tokens):
        raise DVRInputError(
            f"{path}: NRRD field 'sizes': expected 3 integers, got {shown(fields['sizes'])}"
        )
    dims = tuple(parse_int(s, path, "sizes", lo=0) for s in tokens)
    if 0 in dims:
        raise DVRInputError(f"{path}: the volume is empty (NRRD sizes {dims})")
    encoding = _NRRD_ENCODINGS.get(need("encoding").lower())
    if encoding is None:
        raise DVRInputError(
            f"{path}: NRRD encoding {shown(fields['encoding'])} is not supported; expected raw, "
            "gzip or bzip2"
        )
    for key in ("line skip", "byte skip"):
        if fields.get(key, "0").strip() != "0":
            raise DVRInputError(f"{path}: NRRD field {key!r} is not supported (must be 0)")
    endian = "<" if fields.get("endian", "little").lower() == "little" else ">"
    dt = np.dtype(endian + dtype)
    axes, origin = nrrd_axes(fields, path), _nrrd_origin(fields, path)
    if nrrd_space(fields, path) == "ras":
        axes, origin = ras_to_lps(axes, origin)
    elif nrrd_space(fields, path) == "las":
        axes, origin = axes * [[-1.0], [1.0], [1.0]], np.multiply(origin, [-1.0, 1.0, 1.0])
    expected = check_budget(path, dims, dt, limit=limit, hint=hint)
    data_file = fields.get("data file", fields.get("datafile"))
    if data_file is not None:
        if data_file.split()[:1] == ["LIST"] or "%" in data_file:
            raise DVRInputError(f"{path}: NRRD multi-file 'data file' lists are not supported")
        src = resolve_data_file(path, data_file, "data file")
        where, offset = f"{path} (data file {src.name})", 0
    else:
        src, where = path, str(path)
    if check_only:
        return dims, dt, src
    if encoding == "raw":
        check_size(where, src.stat().st_size - offset, expected, dims)
        with open(src, "rb") as f:
            f.seek(offset)
            data = np.fromfile(f, dtype=dt, count=math.prod(dims))
        check_size(where, data.nbytes, expected, dims)  # the file shrank while being read
    else:
        data = read_compressed(src, offset, expected, encoding, where).view(dt)
    data = data.reshape(dims[::-1])
    if not dt.isnative:
        data = data.astype(dt.newbyteorder("="))
    return data, axes, origin, nrrd_oriented(fields)


def nrrd_oriented(fields: dict[str, str]) -> bool:
    """Whether a NRRD header names a patient space (``space``, not a bare ``3D-right-handed``).

    Without it (only ``spacings``, or ``space dimension`` with ``space directions``) the
    axes are taken as L, P, S, which is a guess.
    """
    space = fields.get("space", "").strip().lower()
    return space in _NRRD_SPACES and space != "3d-right-handed"


def nrrd_space(fields: dict[str, str], path: Path) -> str:
    """Return the NRRD ``space`` as ``"lps"``, ``"ras"`` or ``"las"`` (LPS when absent)."""
    if "space" not in fields:
        return "lps"
    got = _NRRD_SPACES.get(fields["space"].strip().lower())
    if got is None:
        raise DVRInputError(
            f"{path}: NRRD field 'space': {shown(fields['space'])} is not supported; expected "
            "one of left-posterior-superior, right-anterior-superior, left-anterior-superior, "
            "scanner-xyz, 3D-right-handed"
        )
    return got


def nrrd_axes(fields: dict[str, str], path: Path) -> np.ndarray:
    """Columns: the world vector of one step along index x, y, z (``space directions``)."""
    if "space directions" in fields:
        text = fields["space directions"]
        if len(text) > 8 * MAX_TOKEN:
            raise DVRInputError(f"{path}: NRRD field 'space directions' is too long")
        vecs = re.findall(r"\(([^)]*)\)|none", text)
        rows = [nrrd_vector(v, path, "space directions") for v in vecs if v]
        if len(rows) != 3 or any(len(r) != 3 for r in rows):
            raise DVRInputError(f"{path}: NRRD field 'space directions': expected 3 vectors")
        mat = np.array(rows)
        with np.errstate(over="ignore"):
            lengths = np.linalg.norm(mat, axis=1)
        check_spacing(lengths, path, "space directions")
        return mat.T
    return np.diag(_nrrd_spacing(fields, path))


def _nrrd_spacing(fields: dict[str, str], path: Path) -> tuple[float, float, float]:
    if "spacings" in fields:
        vals = fields["spacings"].split()
        if len(vals) != 3:
            raise DVRInputError(
                f"{path}: NRRD field 'spacings': expected 3 values, got {shown(fields['spacings'])}"
            )
        return check_spacing([parse_float(v, path, "spacings") for v in vals], path, "spacings")
    return (1.0, 1.0, 1.0)


def _nrrd_origin(fields: dict[str, str], path: Path) -> tuple[float, float, float]:
    if "space origin" not in fields:
        return (0.0, 0.0, 0.0)
    text = fields["space origin"]
    if len(text) > 4 * MAX_TOKEN:
        raise DVRInputError(f"{path}: NRRD field 'space origin' is too long")
    org = nrrd_vector(text, path, "space origin")
    if len(org) != 3:
        raise DVRInputError(f"{path}: NRRD field 'space origin': expected 3 numbers, got {org}")
    return org  # type: ignore[return-value]


def write_nrrd(volume: Volume, target: Path, *, detached: bool) -> list[Path]:
    data = volume.data
    code = data.dtype.str[1:]
    if code not in NRRD_NAMES:
        raise DVRInputError(f"{target.name}: NRRD cannot store dtype {data.dtype}")
    x, y, z = volume.dims
    lines = [
        "NRRD0004",
        "# written by dvr_perception",
        f"type: {NRRD_NAMES[code]}",
        "dimension: 3",
        f"sizes: {x} {y} {z}",
        "kinds: domain domain domain",
        # no patient space for a volume whose file recorded none (read back as not oriented)
        "space: left-posterior-superior" if volume.oriented else "space dimension: 3",
        "space directions: "
        + " ".join(
            "(" + ",".join(repr(float(v)) for v in np.asarray(volume.direction)[:, i] * s) + ")"
            for i, s in enumerate(volume.spacing)
        ),
        "space origin: (" + ",".join(repr(o) for o in volume.origin) + ")",
        "endian: little",
        "encoding: raw",
    ]
    # the data written from the array itself (a view on little-endian machines): a copy of a
    # large volume's bytes was a transient peak of its size
    payload = np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("<")).reshape(-1)
    if not detached:
        with target.open("wb") as f:
            f.write(("\n".join(lines) + "\n\n").encode("ascii"))
            f.write(payload.view(np.uint8))
        return [target]
    stem = target.name[: -len(".nhdr")]
    raw = target.with_name(f"{stem}_{x}x{y}x{z}_{data.dtype.name}.raw")
    with raw.open("wb") as f:
        f.write(payload.view(np.uint8))
    target.write_text("\n".join([*lines, f"data file: {raw.name}"]) + "\n", encoding="ascii")
    return [raw, target]
