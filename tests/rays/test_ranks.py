"""The ray analysis over ranks (``dvr_perception.rays.ranks``) and its messages
(``dvr_perception.parallel``), with the ranks as threads of one process.

Under ParaView's MPI the same code runs with a ``VTKCommunicator``
(``tests/plugin/test_mpi_ranks.py``).
"""

from __future__ import annotations

import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dvr_perception.errors import DVRInputError
from dvr_perception.measures import all_measures
from dvr_perception.parallel import (
    SerialCommunicator,
    communicator,
    local_group,
    pack_arrays,
    unpack_arrays,
)
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.rays.ranks import (
    analyze_in_threads,
    block_split,
    ghost_levels,
    owned_voxels,
    piece_curvature,
    piece_of,
)
from dvr_perception.structures.phantom import make_phantom


def _run(n, function):
    out = {}

    def rank(c):
        try:
            out[c.rank] = function(c)
        except BaseException as exc:
            out[c.rank] = exc

    threads = [threading.Thread(target=rank, args=(c,)) for c in local_group(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for r in range(n):
        if isinstance(out[r], BaseException):
            raise out[r]
    return [out[r] for r in range(n)]


def test_pack_round_trip_keeps_dtypes_shapes_and_empty_arrays():
    arrays = {
        "st": np.random.default_rng(0).random((5, 7)),
        "bits": np.arange(5, dtype=np.uint32),
        "none": np.zeros((0, 3), np.float32),
        "flag": np.array([True, False]),
        "scalar": np.float64(2.5),
    }
    got = unpack_arrays(pack_arrays(arrays))
    assert list(got) == list(arrays)
    for k, v in arrays.items():
        assert got[k].dtype == np.asarray(v).dtype
        assert np.array_equal(got[k], v)
    with pytest.raises(DVRInputError, match="Python objects"):
        pack_arrays({"o": np.array([object()])})
    with pytest.raises(DVRInputError, match="left over"):
        unpack_arrays(np.concatenate([pack_arrays({"a": np.ones(2)}), np.zeros(3, np.uint8)]))


def test_serial_communicator_collectives_return_their_input():
    c = communicator()
    assert isinstance(c, SerialCommunicator)
    assert (c.rank, c.size) == (0, 1)
    assert c.allreduce_min_max(3.0, 4.0) == (3.0, 4.0)
    assert c.gather({"a": 1}) == [{"a": 1}]
    assert c.allgather(5) == [5]
    assert c.broadcast({"x": np.ones(2)})["x"].tolist() == [1.0, 1.0]
    with pytest.raises(DVRInputError, match="not another rank"):
        c.send({"x": np.ones(1)}, 0)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_thread_group_collectives_and_point_to_point(n):
    def body(c):
        lo, hi = c.allreduce_min_max(float(c.rank), 2.0 * c.rank)
        mx = c.allreduce_max([c.rank, -c.rank])
        b = c.broadcast({"v": np.arange(4) * 3} if c.rank == 1 else None, root=1)
        if c.rank == 0:
            c.send({"x": np.full(3, 7.0)}, n - 1)
        got = c.recv(0)["x"].tolist() if c.rank == n - 1 else None
        c.barrier()
        return lo, hi, mx.tolist(), b["v"].tolist(), got, c.gather(c.rank), c.allgather(-c.rank)

    out = _run(n, body)
    for r, (lo, hi, mx, b, got, gathered, every) in enumerate(out):
        assert (lo, hi) == (0.0, 2.0 * (n - 1))
        assert mx == [n - 1, 0]
        assert b == [0, 3, 6, 9]
        assert got == ([7.0] * 3 if r == n - 1 else None)
        assert gathered == (list(range(n)) if r == 0 else None)
        assert every == [-i for i in range(n)]


@pytest.mark.parametrize(("shape", "n"), [((10, 12, 9), 2), ((10, 12, 9), 4), ((5, 30, 7), 3)])
def test_block_split_partitions_cells_and_owned_voxels_partition_voxels(shape, n):
    bricks = block_split(shape, n)
    assert len(bricks) == n
    cells = np.zeros([s - 1 for s in shape], int)
    voxels = np.zeros(shape, int)
    for b in bricks:
        cells[tuple(slice(c0, c1) for c0, c1 in b.cells)] += 1
        voxels[tuple(slice(a, c) for a, c in owned_voxels(b, shape))] += 1
    assert (cells == 1).all()
    assert (voxels == 1).all()


def test_ghost_levels_cover_the_curvature_kernel():
    assert ghost_levels((1, 1, 1), None) == 1
    assert ghost_levels((1, 1, 1), 1.0) == 4
    assert ghost_levels((1, 1, 2), 1.0) == 4  # z: 2 voxels, x/y: 4
    assert ghost_levels((1, 1, 1), 2.0) == 7


@pytest.mark.parametrize("n", [2, 4])
def test_piece_curvature_equals_the_whole_volumes_on_each_brick(n):
    vol, spec = make_phantom(size=28)
    whole, _ = curvature_volume(vol, spec, sigma=1.0)
    ghost = ghost_levels(vol.spacing, 1.0)
    bricks = block_split(vol.data.shape, n)

    def body(c):
        piece = piece_of(vol, bricks[c.rank], ghost)
        return piece, piece_curvature(c, piece, spec, 1.0)

    for piece, curv in _run(n, body):
        corners = tuple((c0, c1 + 1) for c0, c1 in piece.brick.cells)
        glob = tuple(slice(a, b) for a, b in corners)
        assert np.array_equal(curv[piece.local(corners)], whole[glob])


@pytest.mark.parametrize("n", [2, 4])
def test_ranks_in_threads_equal_the_serial_analysis(n):
    vol, spec = make_phantom(size=28)
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=24, height=20)
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    # a one-shot rank analysis can neither re-composite nor walk the whole volume again, so
    # it reads enclosers against their plain view: so does a copy of the serial analysis
    # that the engine did not make (the serial filter's reading is RankSession's, D7)
    serial = replace(analyze(vol, spec, cam, curvature=curv, build_cache=False))
    got, records = analyze_in_threads(vol, spec, cam, n)
    assert np.array_equal(got.rgba, serial.rgba)
    for a, b in zip(all_measures(got, spec), all_measures(serial, spec), strict=True):
        assert np.allclose(a.deviation, b.deviation, equal_nan=True)
    assert [r["rank"] for r in records] == list(range(n))
    assert sum(r["voxels"] for r in records) < 2 * vol.data.size


@pytest.mark.shared_data
@pytest.mark.parametrize("n", [2, 4])
def test_ranks_in_threads_equal_the_serial_measures_on_neghip(shared_data, n):
    from dvr_perception.structures.io import load_spec
    from dvr_perception.volume import load_volume

    vol = load_volume(shared_data / "neghip.nhdr")
    spec = load_spec(Path(__file__).resolve().parents[2] / "state_files" / "neghip.json")
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=32, height=32)
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    # a one-shot rank analysis can neither re-composite nor walk the whole volume again, so
    # it reads enclosers against their plain view: so does a copy of the serial analysis
    # that the engine did not make (the serial filter's reading is RankSession's, D7)
    serial = replace(analyze(vol, spec, cam, curvature=curv, build_cache=False))
    got, records = analyze_in_threads(vol, spec, cam, n)
    es = all_measures(serial, spec)
    eg = all_measures(got, spec)
    assert (eg[0].E_v, eg[1].E_s, eg[2].E_t) == (es[0].E_v, es[1].E_s, es[2].E_t)
    share = {2: 0.60, 4: 0.35}[n]
    assert max(r["voxels"] for r in records) <= share * vol.data.size


# -- the optimiser over ranks (RankSession / RankCache) -------------------------------------------
def _session_reevaluations(vol, spec, cam, n, params):
    """Rank 0's re-evaluations of ``params`` (a list of kwargs) over ``n`` thread ranks."""
    from dvr_perception.distributed import RankSession

    ghost = ghost_levels(vol.spacing, 1.0)
    bricks = block_split(vol.data.shape, n)

    def rank(c):
        session = RankSession(c, piece_of(vol, bricks[c.rank], ghost), spec)
        if c.rank != 0:
            return session.serve()
        analysis = session.analyze(cam)
        got = [analysis] + [analysis.cache.reevaluate(**p) for p in params]
        session.stop()
        return got

    return _run(n, rank)[0]


@pytest.mark.parametrize("n", [2, 3])
def test_rank_cache_reevaluates_new_opacities_colours_and_light_as_the_whole_cache(n):
    from dvr_perception.rays.engine import reevaluate
    from dvr_perception.structures.spec import Lighting

    vol, spec = make_phantom(size=28)
    cam = Camera.from_view(vol.bounds, azimuth=35, elevation=25, width=24, height=20)
    k = len(spec.structures)
    params = [
        {"opacities": np.linspace(0.9, 0.2, k)},
        {"colours": np.tile([0.2, 0.7, 0.4], (k, 1)), "light_direction": (0.3, 0.5, 0.8)},
        {"lighting": [Lighting(0.2, 0.6, 0.5, 30.0)] * k, "opacities": np.full(k, 0.35)},
    ]
    curvature, _ = curvature_volume(vol, spec)
    whole = analyze(vol, spec, cam, curvature=curvature, build_cache=True)
    got = _session_reevaluations(vol, spec, cam, n, params)
    expect = [whole] + [reevaluate(whole.cache, **p) for p in params]
    assert got[0].cache.present is not None
    for a, b in zip(got, expect, strict=True):
        for name in ("rgba", "image", "accumulated", "visible", "curvature", "present"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    # the re-evaluations changed the picture (the test can fail)
    assert not np.array_equal(got[1].rgba, got[0].rgba)
    assert not np.array_equal(got[2].rgba, got[1].rgba)


@pytest.mark.parametrize("n", [2, 4])
def test_optimize_over_ranks_in_threads_equals_the_serial_optimisation(n):
    from dvr_perception.distributed import optimize_in_threads
    from dvr_perception.optimize import optimize

    vol, spec = make_phantom(size=24)
    cam = Camera.from_view(vol.bounds, azimuth=30, elevation=20, width=40, height=32)
    opts = {"stages": ("opacity", "lighting", "colour"), "max_iter": 2, "resolution": 24}
    serial = optimize(vol, spec, cam, **opts)
    res, records = optimize_in_threads(vol, spec, cam, n, **opts)
    for key in ("E_v", "E_s", "E_t", "E"):
        assert res.initial[key] == serial.initial[key], key
        assert res.final[key] == serial.final[key], key
    assert serial.final["E"] < serial.initial["E"]  # it optimised something
    np.testing.assert_array_equal(
        [s.render_opacity for s in res.spec.structures],
        [s.render_opacity for s in serial.spec.structures],
    )
    assert [r["rank"] for r in records] == list(range(n))
    assert sorted(r["order"] for r in records) == list(range(n))
    evals = {r["evaluations"] for r in records}
    assert len(evals) == 1  # every rank took part in every evaluation
    assert evals.pop() > 10
    total = np.prod(vol.data.shape)
    assert all(r["voxels"] < total for r in records)
    assert all(r["views"] >= 2 for r in records)  # the user view and the optimisation view


def test_rank_session_refuses_commands_from_other_ranks():
    from dvr_perception.distributed import RankSession

    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    bricks = block_split(vol.data.shape, 2)

    def rank(c):
        session = RankSession(c, piece_of(vol, bricks[c.rank], ghost_levels(vol.spacing, 1.0)),
                              spec)  # fmt: skip
        if c.rank == 1:
            with pytest.raises(DVRInputError, match="rank 1 cannot give commands"):
                session.analyze(cam)
            return session.serve()
        return session.stop()

    records = _run(2, rank)[0]
    assert [r["evaluations"] for r in records] == [0, 0]


def test_abort_on_error_ends_the_job_with_one_line_and_the_status(capsys):
    from dvr_perception.parallel import RankFailure, abort_on_error

    def leave(status):
        raise RankFailure(status)

    c1 = local_group(2)[1]
    with pytest.raises(RankFailure) as exc, abort_on_error(c1, "Perception Measures", exit=leave):
        raise ValueError("boom\non two lines")
    assert exc.value.args == (1,)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "dvr-perception: error: Perception Measures (rank 1): ValueError: boom on two lines"
    ]
    # one rank: the exception is the caller's
    with (
        pytest.raises(DVRInputError, match="bad"),
        abort_on_error(SerialCommunicator(), "x", exit=leave),
    ):
        raise DVRInputError("bad")


@pytest.mark.parametrize("name", ["RankCache", "RankSession", "optimize_in_threads", "warm_up"])
def test_the_drivers_old_path_warns_and_still_works(name):
    import dvr_perception.distributed as new
    from dvr_perception.rays import ranks as old

    with pytest.warns(DeprecationWarning, match=rf"dvr_perception\.distributed\.{name}"):
        got = getattr(old, name)
    assert got is getattr(new, name)
