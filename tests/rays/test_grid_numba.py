"""The numba twins of the per-volume passes equal the numpy originals value for value."""

from __future__ import annotations

import numpy as np
import pytest

from dvr_perception.rays import _grid, engine
from dvr_perception.structures.io import load_spec
from dvr_perception.structures.phantom import make_phantom
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.io import load_volume
from dvr_perception.volume.volume import Volume

pytest.importorskip("numba")


def _passes(vol, spec, monkeypatch, numba: bool):
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "" if numba else "1")
    fresh = Volume(vol.data, vol.spacing, vol.origin, labels=vol.labels)  # an empty memo
    lut = build_lut(spec, scalar_range=vol.scalar_range, dtype=vol.data.dtype)
    labmap, ids, memb = engine._with_labels(fresh, spec, lut)
    idx = _grid.index_volume(fresh, lut.lo, lut.scale, lut.size)
    cells = _grid.cell_map(fresh, idx, ids, memb, labmap)
    return idx, _grid.normal_codes(fresh), cells, _grid.voxel_records(fresh, idx, cells)


def _check(vol, spec, monkeypatch):
    idx, codes, cells, rec_np = _passes(vol, spec, monkeypatch, numba=False)
    idx2, codes2, cells2, rec_nb = _passes(vol, spec, monkeypatch, numba=True)
    assert np.array_equal(idx, idx2)
    assert np.array_equal(codes, codes2)
    assert np.array_equal(cells, cells2)
    # records: the same index everywhere, the same code wherever shading can read it
    assert np.array_equal(rec_np & 0xFFFF, rec_nb & 0xFFFF)
    read = np.zeros(cells.shape, bool)
    busy = cells[:-1, :-1, :-1] != _grid.CELL_EMPTY
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                read[dz : dz + busy.shape[0], dy : dy + busy.shape[1], dx : dx + busy.shape[2]] |= (
                    busy
                )
    assert read.any()
    assert np.array_equal((rec_np >> 16)[read], (rec_nb >> 16)[read])
    assert np.all((rec_nb >> 16)[~read] == _grid.ZERO_CODE)


def test_phantom_with_labels_and_anisotropic_spacing(monkeypatch):
    vol, spec = make_phantom(size=24)
    vol = Volume(vol.data, (1.0, 0.7, 2.5), labels=vol.labels)
    _check(vol, spec, monkeypatch)


@pytest.mark.parametrize("name", ["engine", "cthead", "tooth", "neghip", "bonsai"])
def test_shared_volumes(shared_data, name, monkeypatch):
    vol = load_volume(shared_data / f"{name}.nhdr")
    _check(vol, load_spec(f"state_files/{name}.json"), monkeypatch)


@pytest.mark.parametrize("ulp", [1.0, -1.0, 4.0, -4.0])
def test_normal_codes_do_not_follow_numpys_arctan2_and_arcsin_rounding(
    shared_data, monkeypatch, ulp
):
    """numpy's SIMD arctan2/arcsin differ from the C library's by an ulp, differently in numpy
    1.24 (ParaView) and 2.x; codes on a rounding boundary (phi = 45 degrees) must not move."""
    vol = load_volume(shared_data / "fuel.nhdr")
    monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "1")
    exact = _grid.normal_codes(Volume(vol.data, vol.spacing, vol.origin))
    for name in ("arctan2", "arcsin"):
        func = getattr(np, name)
        monkeypatch.setattr(np, name, lambda *a, f=func: f(*a) * (1.0 + ulp * 2.0**-52))
    off = _grid.normal_codes(Volume(vol.data, vol.spacing, vol.origin))
    monkeypatch.undo()
    assert np.array_equal(off, exact)
    nb = _grid.normal_codes(Volume(vol.data, vol.spacing, vol.origin))  # the C library's angles
    assert np.array_equal(nb, exact)


@pytest.mark.parametrize("shape", [(9, 6, 13), (5, 5, 5), (2, 17, 4), (2, 2, 3)])
def test_the_block_map_of_numba_equals_numpys(monkeypatch, shape):
    """Blocks of 4^3 cells, those reaching past the grid too (issue 31: numba's empty blocks)."""
    rng = np.random.default_rng(sum(shape))
    for density in (0.0, 0.01, 0.2):
        cells = np.where(rng.random(shape) < density, 255, 0).astype(np.uint8)
        got = {}
        for numba in (False, True):
            monkeypatch.setenv("DVR_PERCEPTION_NO_NUMBA", "" if numba else "1")
            vol = Volume(np.zeros(shape, np.uint8))  # an empty memo
            got[numba] = _grid.block_map(vol, cells)
        assert got[True].shape == got[False].shape
        assert np.array_equal(got[True], got[False])
    assert got[True].shape == tuple(-(-(n - 1) // 4) for n in shape)
