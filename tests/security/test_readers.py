"""Readers: compressed data is bounded by the header, valid compressed volumes still load."""

from __future__ import annotations

import bz2
import gzip
import resource
import time

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.volume._limits import read_compressed, resolve_data_file
from dvr_perception.volume.io import load_volume

HEAD = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 8\nencoding: {enc}\n"


@pytest.mark.parametrize(("enc", "pack"), [("gzip", gzip.compress), ("bzip2", bz2.compress)])
def test_compressed_volume_loads(tmp_path, enc, pack):
    values = (np.arange(512) % 251).astype(np.uint8)
    path = tmp_path / "v.nrrd"
    path.write_bytes((HEAD.format(enc=enc) + "\n").encode() + pack(values.tobytes()))
    np.testing.assert_array_equal(load_volume(path).data.ravel(), values)


@pytest.mark.parametrize(("enc", "pack"), [("gzip", gzip.compress), ("bzip2", bz2.compress)])
def test_compressed_truncated_and_too_long(tmp_path, enc, pack):
    path = tmp_path / "v.nrrd"
    path.write_bytes((HEAD.format(enc=enc) + "\n").encode() + pack(bytes(500)))
    with pytest.raises(DVRInputError, match="expands to 500 bytes, the header's sizes need 512"):
        load_volume(path)
    path.write_bytes((HEAD.format(enc=enc) + "\n").encode() + pack(bytes(513)))
    with pytest.raises(DVRInputError, match="more than the 512 bytes"):
        load_volume(path)


def test_bzip2_bomb_stops_at_the_header_size(tmp_path):
    """bzip2 has no useful ratio bound (1 MB of zeros packs into ~50 bytes): the stream is cut."""
    blob = bz2.compress(bytes(1 << 20), 1) * 200  # 200 concatenated streams of 1 MB each
    assert len(blob) < 20_000
    src = tmp_path / "bomb.bz2"
    src.write_bytes(blob)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with pytest.raises(DVRInputError, match="more than the 4096 bytes"):
        read_compressed(src, 0, 4096, "bzip2", src)
    assert time.perf_counter() - t0 < 2.0
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 50


def test_data_file_may_lie_in_a_subfolder(tmp_path):
    (tmp_path / "raw").mkdir()
    (tmp_path / "raw" / "d.raw").write_bytes(bytes(512))
    assert resolve_data_file(tmp_path / "h.nhdr", "raw/d.raw", "data file").parent.name == "raw"
    with pytest.raises(DVRInputError, match="outside the header's folder"):
        resolve_data_file(tmp_path / "raw" / "h.nhdr", "../raw/../../x", "data file")


def test_allow_data_root_must_be_a_folder(tmp_path, capsys):
    from dvr_perception.cli import main

    argv = ["render", "phantom", "--allow-data-root", str(tmp_path / "nope"),
            "--out", str(tmp_path / "x.png")]  # fmt: skip
    assert main(argv) == 2
    assert "--allow-data-root" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
