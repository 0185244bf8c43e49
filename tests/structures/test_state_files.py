"""The shipped state_files/*.json presets: one per shared dataset, valid, round-tripping."""

from __future__ import annotations

from pathlib import Path

import pytest

from dvr_perception.structures import check_spec_for_volume, load_spec, spec_from_dict, spec_to_dict
from dvr_perception.volume import load_volume

STATE_DIR = Path(__file__).resolve().parents[2] / "state_files"
STEMS = sorted(p.stem for p in STATE_DIR.glob("*.json"))
DATASETS = {
    "HeadMRVolume", "aneurism", "bonsai", "bucky", "cthead", "engine", "fuel", "headsq_quarter",
    "hydrogen_atom", "ironProt", "lidc_chest", "lobster", "neghip", "nucleon", "tooth",
    "vispy_mri_head",
}  # fmt: skip


def test_one_preset_per_dataset():
    assert set(STEMS) == DATASETS


@pytest.mark.parametrize("stem", STEMS)
def test_preset_is_valid_and_round_trips(stem):
    spec = load_spec(STATE_DIR / f"{stem}.json")
    assert 2 <= len(spec.structures) <= 5
    assert all(s.range is not None for s in spec.structures)
    assert spec_from_dict(spec_to_dict(spec)) == spec


@pytest.mark.shared_data
@pytest.mark.parametrize("stem", STEMS)
def test_every_range_holds_voxels(stem, shared_data):
    spec = load_spec(STATE_DIR / f"{stem}.json")
    vol = load_volume(shared_data / f"{stem}.nhdr")
    assert check_spec_for_volume(spec, vol) == []
    lo, hi = vol.scalar_range
    for s in spec.structures:
        assert lo <= s.range[1]
        assert s.range[0] <= hi
