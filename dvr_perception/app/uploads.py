"""Safety checks of an uploaded volume file, before any reader sees it.

A hostile upload may name a *detached* data file anywhere on the server (``data file:`` in a
NRRD header, ``ElementDataFile`` in a MetaImage header), or be a small compressed file whose
voxel data expands to gigabytes.  :func:`check_volume_bytes` refuses both without reading any
other file and without holding the decompressed data.  The header is parsed by the very
functions :func:`dvr_perception.volume.load_volume` reads it with
(:func:`dvr_perception.volume.io.check_volume_file`), so what is sized here is what is read
later: no second parser to disagree with.  Its sizes must fit ``--max-volume-mb``, any
detached data file is refused, and compressed data is streamed through a bounded
decompressor, counting (and dropping) the bytes, to check that it holds exactly what the
header claims.  Only then is the file handed to the volume reader.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import zlib
from pathlib import Path

from dvr_perception.errors import DVRInputError

__all__ = ["check_volume_bytes"]

#: Bytes decompressed per step by the bounded decompressor.
STEP_BYTES = 1 << 20
#: Largest header read (NRRD, MetaImage, VTI).
HEADER_BYTES = 65536


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


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
            raise DVRInputError(f"{name}: corrupt gzip data ({exc})") from None
        total += len(out)
        if total > expected:
            raise DVRInputError(
                f"{name}: the compressed data expands beyond the {_mb(expected)} its "
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
            raise DVRInputError(f"{name}: truncated gzip data")


_HINT = "--max-volume-mb (the upload limit)"


def check_volume_bytes(name: str, content: bytes, *, max_volume_bytes: int) -> None:
    r"""Refuse an uploaded file that names another file or holds too much voxel data.

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

    Examples
    --------
    >>> head = b"NDims = 3\nDimSize = 2 2 2\nElementType = MET_UCHAR\n"
    >>> check_volume_bytes("a.mha", head + b"ElementDataFile = LOCAL\n" + bytes(8),
    ...                    max_volume_bytes=8)
    >>> check_volume_bytes("a.mha", head + b"ElementDataFile = /etc/passwd\n",
    ...                    max_volume_bytes=8)
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: upload a.mha: the header names a detached data file ('/etc/passwd'); upload a single-file volume with its data attached
    """  # noqa: E501
    low = name.lower()
    if low.endswith((".nhdr", ".mhd")):
        raise DVRInputError(
            f"upload {name}: a detached header needs its data file; upload a single-file volume "
            "(.nrrd, .mha, .vti, .nii, .nii.gz) instead"
        )
    folder = Path(tempfile.mkdtemp(prefix="dvr-upload-check-"))
    try:
        path = folder / Path(name).name
        path.write_bytes(content)
        try:
            _check_file(path, low, max_volume_bytes)
        except DVRInputError as exc:
            why = str(exc).replace(f"{path}: ", "").replace(str(path), name)
            if not any(word in why for word in ("detached", "--max-volume-mb", "expands")):
                why = f"not a readable volume ({why})"
            raise DVRInputError(f"upload {name}: {why}") from None
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _check_file(path: Path, low: str, limit: int) -> None:
    """Run the upload's checks on its temporary copy (the caller renames it in messages)."""
    from dvr_perception.volume._headers import meta_fields
    from dvr_perception.volume._nrrd import nrrd_header
    from dvr_perception.volume.io import check_volume_file

    offset, compressed = None, False
    if low.endswith(".nrrd"):
        fields, offset = nrrd_header(path)
        detached = fields.get("data file", fields.get("datafile"))
        compressed = fields.get("encoding", "raw").lower() in ("gzip", "gz")
    elif low.endswith(".mha"):
        fields, offset = meta_fields(path)
        detached = fields["ElementDataFile"]
        detached = None if detached in ("LOCAL", "Local", "local") else detached
        compressed = fields.get("CompressedData", "False").strip().lower() in ("true", "1")
    else:
        detached = None
    if detached is not None:
        raise DVRInputError(
            f"the header names a detached data file ({detached!r}); upload a single-file "
            "volume with its data attached"
        )
    dims, dtype, _ = check_volume_file(path, limit=limit, hint=_HINT)
    if dims is None:
        return
    content = path.read_bytes()
    expected = math.prod(dims) * dtype.itemsize
    if compressed:
        _inflated_size(path.name, content[offset:], expected)
    elif low.endswith(".nii.gz"):
        # the whole file is one gzip stream: bound it by the largest data allowed (+ header)
        _inflated_size(path.name, content, limit + HEADER_BYTES)
