"""The app's own checks of an uploaded file: no detached data, bounded decompressed size."""

from __future__ import annotations

import gzip
import struct
import tracemalloc
import zlib

import numpy as np
import pytest

from dvr_perception.app.uploads import check_volume_bytes
from dvr_perception.errors import DVRInputError

LIMIT = 64 * 2**20


def _nrrd(sizes: str, encoding: str = "raw", extra: str = "") -> bytes:
    head = f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {sizes}\nencoding: {encoding}\n{extra}\n"
    return head.encode()


def test_a_good_gzip_nrrd_passes():
    data = np.arange(32 * 32 * 32, dtype=np.uint8).tobytes()
    check_volume_bytes(
        "ok.nrrd", _nrrd("32 32 32", "gzip") + gzip.compress(data), max_volume_bytes=LIMIT
    )


def test_a_gzip_bomb_is_refused_without_inflating_it():
    bomb = _nrrd("64 64 64", "gzip") + gzip.compress(b"\0" * (256 * 2**20), 9)  # ~250 kB
    tracemalloc.start()
    try:
        with pytest.raises(DVRInputError, match="expands beyond"):
            check_volume_bytes("bomb.nrrd", bomb, max_volume_bytes=LIMIT)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20  # a few inflate steps, never the 256 MB


def test_a_header_claiming_more_than_the_limit_is_refused():
    with pytest.raises(DVRInputError, match=r"field 'sizes'.*need 1\.00 GB.*--max-volume-mb"):
        check_volume_bytes("big.nrrd", _nrrd("1024 1024 1024", "gzip"), max_volume_bytes=LIMIT)


@pytest.mark.parametrize("field", ["data file: ../outside/secret.bin", "datafile: /etc/passwd"])
def test_a_detached_nrrd_data_file_is_refused(field):
    with pytest.raises(DVRInputError, match="detached data file"):
        check_volume_bytes("d.nrrd", _nrrd("4 4 4", extra=field + "\n"), max_volume_bytes=LIMIT)


def test_a_detached_metaimage_data_file_is_refused():
    head = b"ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\n"
    with pytest.raises(DVRInputError, match="detached data file"):
        check_volume_bytes(
            "d.mha", head + b"ElementDataFile = ../../etc/passwd\n", max_volume_bytes=LIMIT
        )


def test_a_compressed_metaimage_bomb_is_refused():
    head = b"NDims = 3\nDimSize = 8 8 8\nElementType = MET_UCHAR\nCompressedData = True\n"
    body = zlib.compress(b"\0" * (64 * 2**20), 9)
    with pytest.raises(DVRInputError, match="expands beyond"):
        check_volume_bytes(
            "b.mha", head + b"ElementDataFile = LOCAL\n" + body, max_volume_bytes=LIMIT
        )


def test_a_nifti_gz_bomb_is_refused():
    header = bytearray(352)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, 3, 8, 8, 8, 1, 1, 1, 1)
    struct.pack_into("<hh", header, 70, 2, 8)  # datatype uint8, bitpix 8
    struct.pack_into("<f", header, 108, 352.0)
    header[344:348] = b"n+1\0"
    # VTK would read the first 512 bytes only; the upload may expand to at most the limit
    bomb = gzip.compress(bytes(header) + b"\0" * (2 * LIMIT), 9)
    with pytest.raises(DVRInputError, match="expands beyond"):
        check_volume_bytes("b.nii.gz", bomb, max_volume_bytes=LIMIT)


@pytest.mark.parametrize("name", ["a.nhdr", "a.mhd"])
def test_detached_headers_are_refused(name):
    with pytest.raises(DVRInputError, match="detached header"):
        check_volume_bytes(name, b"whatever", max_volume_bytes=LIMIT)


def test_truncated_gzip_is_refused():
    data = gzip.compress(bytes(range(256)) * 64)[:-30]
    with pytest.raises(DVRInputError, match=r"truncated|corrupt"):
        check_volume_bytes("t.nrrd", _nrrd("16 16 64", "gzip") + data, max_volume_bytes=LIMIT)
