"""Presets pair with a volume by the checksum of its data, never by its file name."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.structures import load_spec
from dvr_perception.structures.presets import (
    choose_spec,
    data_checksum,
    data_fingerprint,
    load_preset,
    match_preset,
    preset_names,
    presets_dir,
)
from dvr_perception.volume import Volume, load_volume, save_volume

STEMS = sorted(p.stem for p in presets_dir().glob("*.json"))


def _ct(seed=0, shape=(6, 7, 8)):
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 40, shape).astype(np.uint8)
    data[2:4, 2:5, 2:6] = 200 + rng.integers(0, 40, (2, 3, 4))
    return Volume(data, name="small")


def _write_preset(folder: Path, name: str, volume) -> Path:
    path = folder / f"{name}.json"
    d = {
        "version": 1,
        "structures": [{"name": "dense", "range": [150, 255], "importance": 0.9,
                        "color": [1, 1, 1]}],
        "data": data_fingerprint(volume),
    }  # fmt: skip
    path.write_text(json.dumps(d), encoding="utf-8")
    return path


def test_checksum_is_sha256_of_dtype_shape_and_little_endian_bytes():
    a = np.arange(24, dtype="<i2").reshape(2, 3, 4)
    want = hashlib.sha256(b"int16:(2, 3, 4):" + a.tobytes()).hexdigest()
    assert data_checksum(a) == want
    assert data_checksum(a.astype(">i2")) == want  # a big-endian file: same data
    assert data_checksum(np.asfortranarray(a)) == want  # memory order does not matter
    assert data_checksum(a.reshape(2, 4, 3)) != want  # other dims
    assert data_checksum(a.astype(np.int32)) != want  # other dtype
    b = a.copy()
    b[1, 2, 3] += 1
    assert data_checksum(b) != want  # one voxel


def test_checksum_hashes_large_arrays_in_slabs_like_one_buffer(monkeypatch):
    from dvr_perception.structures import presets

    a = np.arange(5 * 6 * 7, dtype=np.uint16).reshape(5, 6, 7)[:, ::-1, :]  # not contiguous
    whole = data_checksum(a)
    monkeypatch.setattr(presets, "_SLAB_BYTES", 100)  # 1 slice per slab
    assert data_checksum(a) == whole


def test_a_preset_pairs_by_content_in_any_format_and_name(tmp_path):
    vol = _ct()
    folder = tmp_path / "presets"
    folder.mkdir()
    _write_preset(folder, "tooth", vol)
    _write_preset(folder, "other", _ct(seed=1))
    for target in ("renamed.nhdr", "sub/x.vti", "y.mha"):
        path = tmp_path / target
        path.parent.mkdir(exist_ok=True)
        save_volume(vol, path)
        read = load_volume(path)
        assert match_preset(read, folder) == ("tooth", folder / "tooth.json")
        choice = choose_spec(read, folder=folder)
        assert choice.line == "structures: preset 'tooth' (data checksum matches)"
        assert choice.source == str(folder / "tooth.json")
        assert [s.name for s in choice.spec.structures] == ["dense"]


def test_a_file_named_like_a_preset_with_other_content_gets_a_proposal(tmp_path):
    folder = tmp_path / "presets"
    folder.mkdir()
    _write_preset(folder, "tooth", _ct())
    other = _ct(seed=7)
    save_volume(other, tmp_path / "tooth.nhdr")
    read = load_volume(tmp_path / "tooth.nhdr")
    assert match_preset(read, folder) is None
    choice = choose_spec(read, folder=folder)
    assert choice.source == "proposed"
    assert choice.line == "structures proposed from the data (no preset matches this file)"
    assert all(s.name.startswith("class ") for s in choice.spec.structures)


def test_named_preset_and_requested_count_win(tmp_path):
    folder = tmp_path / "presets"
    folder.mkdir()
    vol = _ct()
    _write_preset(folder, "p", vol)
    choice = choose_spec(_ct(seed=3), preset="p", folder=folder)
    assert choice.line == "structures: preset 'p' (given with --preset)"
    choice = choose_spec(vol, n_structures=2, folder=folder)  # a count asks for a proposal
    assert choice.source == "proposed"
    assert len(choice.spec.structures) == 2
    assert choice.line.endswith("(2 requested with --classes)")
    with pytest.raises(DVRInputError, match=r"--preset 'nope': no such preset \(known: p\)"):
        load_preset("nope", folder)


def test_the_data_field_is_not_an_unknown_spec_field(tmp_path):
    path = _write_preset(tmp_path, "x", _ct())
    spec = load_spec(path)  # pytest turns the unknown-field DVRWarning into an error
    assert spec.structures[0].name == "dense"


def test_every_shipped_preset_records_the_data_it_belongs_to():
    assert set(preset_names()) == set(STEMS)
    for stem in STEMS:
        d = json.loads((presets_dir() / f"{stem}.json").read_text(encoding="utf-8"))
        rec = d["data"]
        assert set(rec) == {"dtype", "dims", "sha256"}
        assert rec["dtype"] in ("uint8", "uint16")
        assert len(rec["sha256"]) == 64
        assert int(rec["sha256"], 16) >= 0
        assert len(rec["dims"]) == 3


@pytest.mark.shared_data
@pytest.mark.parametrize("stem", STEMS)
def test_shared_volumes_keep_their_presets_by_checksum(stem, shared_data, tmp_path):
    vol = load_volume(shared_data / f"{stem}.nhdr")
    assert match_preset(vol) == (stem, presets_dir() / f"{stem}.json")
    assert choose_spec(vol).line == f"structures: preset {stem!r} (data checksum matches)"


@pytest.mark.shared_data
def test_a_shared_volume_under_another_name_and_format_keeps_its_preset(shared_data, tmp_path):
    vol = load_volume(shared_data / "neghip.nhdr")
    save_volume(vol, tmp_path / "my_scan.vti")
    assert match_preset(load_volume(tmp_path / "my_scan.vti"))[0] == "neghip"
    # and a file named like a shared volume, holding another one's data, gets that one's
    save_volume(vol, tmp_path / "tooth.nrrd")
    assert match_preset(load_volume(tmp_path / "tooth.nrrd"))[0] == "neghip"
