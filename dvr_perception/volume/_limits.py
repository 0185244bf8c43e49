"""Checks that a volume file's header must pass before any of its data is read.

A header is untrusted input: it names the data file (which must lie inside the header's own
folder, or inside a root the user allowed), and it claims sizes, a type and an encoding from
which the number of bytes to read is computed.  These helpers turn every way a header can lie
or exaggerate into one :class:`~dvr_perception.errors.DVRInputError` naming the file and the
field, before a byte of data is read or decompressed:

* numbers are parsed from short tokens only (:data:`MAX_TOKEN` characters), sizes are whole
  numbers in ``1..MAX_AXIS`` and their product is computed exactly (Python integers, no
  overflow);
* spacings must be finite, positive and at most :data:`MAX_SPACING`;
* the data must fit the memory limit (:func:`dvr_perception._memory.limit`);
* a gzip stream cannot expand more than :data:`MAX_GZIP_RATIO` times, so a header claiming more
  bytes than that from the compressed size is refused before decompressing, and decompression
  (gzip, bzip2) stops as soon as the stream gives more than the header's byte count.
"""

from __future__ import annotations

import bz2
import gzip
import math
import os
import zlib
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError

__all__ = [
    "DATA_ROOTS_ENV",
    "HEADER_MAX",
    "MAX_AXIS",
    "MAX_GZIP_RATIO",
    "MAX_SPACING",
    "MAX_TOKEN",
    "check_budget",
    "check_size",
    "check_spacing",
    "data_roots",
    "parse_float",
    "parse_int",
    "read_compressed",
    "resolve_data_file",
    "shown",
]

#: Environment variable naming extra folders (``os.pathsep``-separated) in which a header's
#: detached data file may lie; the command line's ``--allow-data-root`` sets it.
DATA_ROOTS_ENV = "DVR_PERCEPTION_DATA_ROOTS"
#: Longest number token a header may hold (a 5000-digit number is refused, not parsed).
MAX_TOKEN = 40
#: Largest size along one axis (VTK's extents are 32-bit integers).
MAX_AXIS = 2**31 - 1
#: Largest voxel spacing accepted (world units).
MAX_SPACING = 1e6
#: deflate cannot expand more than about 1032 : 1, so more from a gzip stream is impossible.
MAX_GZIP_RATIO = 1100
_CHUNK = 1 << 20
#: Most bytes of a NRRD or MetaImage header read.
HEADER_MAX = 65536


def shown(text, limit: int = 60) -> str:
    """Return ``repr(text)`` cut to about ``limit`` characters, for error messages.

    Examples
    --------
    >>> shown("1" * 100, 10)
    "'1111111111...' (100 characters)"
    """
    text = str(text)
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}"[:-1] + f"...' ({len(text)} characters)"


def _token(text: str, where, field: str) -> str:
    tok = text.strip()
    if len(tok) > MAX_TOKEN:
        raise DVRInputError(
            f"{where}: field {field!r}: number {shown(tok, 20)} is too long "
            f"(at most {MAX_TOKEN} characters)"
        )
    return tok


def parse_int(text: str, where, field: str, lo: int = 1, hi: int = MAX_AXIS) -> int:
    """Parse a whole number in ``lo..hi`` from a short token.

    Examples
    --------
    >>> parse_int(" 64 ", "h.nhdr", "sizes")
    64
    >>> parse_int("9" * 50, "h.nhdr", "sizes")
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: h.nhdr: field 'sizes': number '99999999999999999999...' (50 characters) is too long (at most 40 characters)
    """  # noqa: E501
    tok = _token(text, where, field)
    try:
        value = int(tok)
    except ValueError:
        raise DVRInputError(
            f"{where}: field {field!r}: expected a whole number, got {shown(tok)}"
        ) from None
    if not lo <= value <= hi:
        raise DVRInputError(f"{where}: field {field!r}: expected {lo} to {hi}, got {value}")
    return value


def parse_float(text: str, where, field: str) -> float:
    """Parse a finite number from a short token.

    Examples
    --------
    >>> parse_float("2.5", "h.mhd", "ElementSpacing")
    2.5
    """
    tok = _token(text, where, field)
    try:
        value = float(tok)
    except ValueError:
        raise DVRInputError(
            f"{where}: field {field!r}: expected numbers, got {shown(tok)}"
        ) from None
    if not math.isfinite(value):
        raise DVRInputError(f"{where}: field {field!r}: expected finite numbers, got {tok}")
    return value


def check_spacing(values, where, field: str) -> tuple[float, float, float]:
    """Return three spacings, each finite, positive and at most :data:`MAX_SPACING`.

    Examples
    --------
    >>> check_spacing([1, 1, 0], "h.nhdr", "spacings")
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: h.nhdr: field 'spacings': every spacing must be a finite number in (0, 1e+06], got [1.0, 1.0, 0.0]
    """  # noqa: E501
    vals = [float(v) for v in values]
    if len(vals) != 3 or not all(math.isfinite(v) and 0 < v <= MAX_SPACING for v in vals):
        raise DVRInputError(
            f"{where}: field {field!r}: every spacing must be a finite number in "
            f"(0, {MAX_SPACING:g}], got {vals}"
        )
    return vals[0], vals[1], vals[2]


def _human(n: float) -> str:
    return f"{n / 2**30:.2f} GB" if n >= 2**30 else f"{n / 2**20:.1f} MB"


def check_budget(
    where,
    dims,
    dtype,
    field: str = "sizes",
    *,
    limit: int | None = None,
    hint: str | None = None,
    nbytes: int | None = None,
    what: str | None = None,
) -> int:
    """Return the data's byte count; refuse sizes whose data cannot fit the memory limit.

    The product is exact (Python integers), so sizes whose product overflows 64 bits are
    refused here rather than wrapping around.  ``limit`` (bytes) and ``hint`` (how to raise
    it) replace the memory limit, e.g. for the web app's ``--max-volume-mb``; ``nbytes`` and
    ``what`` replace the product and its description when several arrays share the sizes.

    Examples
    --------
    >>> check_budget("v.mha", (4, 4, 4), "uint16")
    128
    >>> check_budget("up.mha", (64, 64, 64), "uint8", "DimSize", limit=1000, hint="--max-volume-mb")
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: up.mha: field 'DimSize': sizes 64 64 64 of uint8 need 0.2 MB, more than the limit of 0.0 MB; raise it with --max-volume-mb
    """  # noqa: E501
    from dvr_perception import _memory as memory

    if nbytes is None:
        nbytes = math.prod(int(d) for d in dims) * np.dtype(dtype).itemsize
    cap = memory.limit() if limit is None else int(limit)
    if nbytes > cap:
        sizes = " ".join(str(int(d)) for d in dims)
        kind = what or f"of {np.dtype(dtype).name}"
        name = "the memory limit" if limit is None else "the limit"
        raise DVRInputError(
            f"{where}: field {field!r}: sizes {sizes} {kind} need {_human(nbytes)}, more than "
            f"{name} of {_human(cap)}; raise it with "
            + (hint or f"--memory-limit (or {memory.ENV})")
        )
    return nbytes


def data_roots() -> list[Path]:
    """Return the extra folders allowed for detached data files (:data:`DATA_ROOTS_ENV`)."""
    text = os.environ.get(DATA_ROOTS_ENV, "")
    return [Path(p).resolve() for p in text.split(os.pathsep) if p.strip()]


def resolve_data_file(header: Path, name: str, field: str) -> Path:
    """Return the data file ``name`` that ``header`` refers to, refusing one outside its folder.

    The path is resolved (symbolic links and ``..``) and must lie inside the header's folder
    or inside one of :func:`data_roots`; nothing about a refused path (whether it exists, its
    size) is revealed.

    Examples
    --------
    >>> resolve_data_file(Path("/data/a.nhdr"), "../etc/passwd", "data file")
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: /data/a.nhdr: field 'data file': '../etc/passwd' lies outside the header's folder; allow another folder with --allow-data-root DIR (or DVR_PERCEPTION_DATA_ROOTS)
    """  # noqa: E501
    if not name or "\0" in name:
        raise DVRInputError(f"{header}: field {field!r}: expected a file name, got {shown(name)}")
    folder = header.parent.resolve()
    target = (header.parent / name).resolve()
    for root in (folder, *data_roots()):
        if target == root or root in target.parents:
            break
    else:
        raise DVRInputError(
            f"{header}: field {field!r}: {shown(name)} lies outside the header's folder; allow "
            f"another folder with --allow-data-root DIR (or {DATA_ROOTS_ENV})"
        )
    if not target.is_file():
        raise DVRInputError(f"{header}: field {field!r}: data file {shown(name)} not found")
    return target


def check_ratio(where, compressed: int, expected: int) -> None:
    """Refuse a gzip/zlib stream too short to hold ``expected`` bytes (deflate's bound)."""
    if expected > MAX_GZIP_RATIO * compressed + 4096:
        raise DVRInputError(
            f"{where}: truncated: {compressed} compressed bytes cannot hold the {expected} "
            "bytes the header's sizes need (wrong sizes?)"
        )


def read_compressed(src: Path, offset: int, expected: int, encoding: str, where) -> np.ndarray:
    """Decompress ``src`` from byte ``offset`` into exactly ``expected`` bytes (uint8 array).

    ``encoding`` is ``"gzip"`` or ``"bzip2"``.  The stream is read in chunks into
    a buffer of ``expected`` bytes; a stream that would give more (a decompression bomb) or
    less is refused as soon as that is known, so memory stays bounded by ``expected``.
    """
    compressed = src.stat().st_size - offset
    if encoding == "gzip":
        check_ratio(where, compressed, expected)
    out = np.empty(expected, np.uint8)
    view = memoryview(out)
    got = 0
    try:
        with open(src, "rb") as raw:
            raw.seek(offset)
            opened = gzip.GzipFile(fileobj=raw, mode="rb") if encoding == "gzip" else None
            with opened or bz2.BZ2File(raw, mode="rb") as stream:
                while got < expected:
                    n = stream.readinto(view[got : min(got + _CHUNK, expected)])
                    if not n:
                        break
                    got += n
                extra = len(stream.read(1)) if got == expected else 0
    except (OSError, EOFError, zlib.error, ValueError) as exc:
        raise DVRInputError(f"{where}: corrupt {encoding} data ({exc})") from None
    if got < expected:
        raise DVRInputError(
            f"{where}: truncated: the {encoding} data expands to {got} bytes, the header's "
            f"sizes need {expected}"
        )
    if extra:
        raise DVRInputError(
            f"{where}: the {encoding} data expands to more than the {expected} bytes the "
            "header's sizes need (refused without decompressing further)"
        )
    return out


def check_size(where, found: int, expected: int, dims) -> None:
    """Refuse data of ``found`` bytes where the header's ``dims`` need ``expected``."""
    if found < expected:
        raise DVRInputError(
            f"{where}: truncated: expected {expected} bytes, found {found} (dims {tuple(dims)})"
        )
    if found > expected:
        raise DVRInputError(
            f"{where}: size mismatch: dims {tuple(dims)} need {expected} bytes, found {found} "
            "(wrong dims or dtype?)"
        )
