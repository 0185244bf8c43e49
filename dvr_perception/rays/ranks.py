"""The ray analysis over MPI ranks, each holding one piece of the volume.

Every rank holds the voxels of one box of the whole volume's cells (a
:class:`~dvr_perception.rays.bricks.Brick`) plus :func:`ghost_levels` layers around it, as
ParaView's piece request delivers them (the reader's extent plus ghost levels).  Together the
ranks reproduce the serial *Perception Measures* (boundary curvature, then
:func:`~dvr_perception.rays.engine.analyze`, then the measures):

1. the scalar range and, inside the curvature, the median offset and the maximum gradient are
   global quantities: all-reductions over the ranks (:func:`piece_curvature`), so each rank's
   curvature equals the whole volume's on its brick's voxels bit for bit;
2. the rays are walked brick by brick in view order (:func:`~dvr_perception.rays.bricks.
   view_order`): the first rank starts every ray's state, walks its brick and sends the state
   to the next rank in that order, ...; the last one sends it to rank 0, which finishes the
   analysis (:func:`analyze_ranks`).

The walk is therefore sequential (exact, each rank's memory bounded by its piece), not faster
than one process.  The communication is a :class:`~dvr_perception.parallel.Communicator`
(ParaView's MPI, or threads for tests: :func:`analyze_in_threads`).

The measures and the optimiser over the ranks (:class:`~dvr_perception.distributed.RankSession`,
which re-uses this module's pieces and walk) are the MPI driver of
:mod:`dvr_perception.distributed`, above the optimiser.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.parallel import Communicator, peak_rss_mb
from dvr_perception.volume.volume import Volume

__all__ = [
    "Piece",
    "analyze_in_threads",
    "analyze_ranks",
    "block_split",
    "ghost_levels",
    "owned_voxels",
    "piece_curvature",
    "piece_of",
]


def ghost_levels(spacing, sigma: float | None) -> int:
    """Voxel layers a piece needs around its cells' voxels.

    One for the normals' central differences; with curvature (``sigma`` not None) the
    Gaussian kernels' largest radius (:func:`~dvr_perception.rays.curvature.curvature_ghost`
    less its layer for the boundary test: the voxels a brick reads, its cells' corners, have
    their neighbours inside the radius; tested equal to the whole volume's curvature).

    Examples
    --------
    >>> ghost_levels((1.0, 1.0, 1.0), 1.0), ghost_levels((1.0, 1.0, 2.0), None)
    (4, 1)
    """
    from dvr_perception.rays.curvature import curvature_ghost

    if sigma is None:
        return 1
    return max(1, curvature_ghost(float(sigma), spacing) - 1)


def owned_voxels(brick, shape) -> tuple[tuple[int, int], ...]:
    """Return the half-open voxel ranges ``(z, y, x)`` a brick owns (a partition of voxels).

    Its cells' first corners, and the volume's last voxel plane where its cells reach it.

    Examples
    --------
    >>> from dvr_perception.rays.bricks import Brick
    >>> owned_voxels(Brick(((0, 4), (2, 9), (0, 9))), (10, 10, 10))
    ((0, 4), (2, 10), (0, 10))
    """
    return tuple(
        (c0, n if c1 >= n - 1 else c1) for (c0, c1), n in zip(brick.cells, shape, strict=True)
    )


def block_split(shape, n: int) -> list:
    """Cut a volume of ``shape`` voxels ``(z, y, x)`` into ``n`` bricks.

    The box's axis with the most cells is cut first, as VTK's block split
    (``vtkExtentTranslator``) does.

    Examples
    --------
    >>> [b.cells for b in block_split((5, 9, 9), 2)]
    [((0, 4), (0, 4), (0, 8)), ((0, 4), (4, 8), (0, 8))]
    """
    from dvr_perception.rays.bricks import Brick

    def cut(box, k):
        if k == 1:
            return [box]
        sizes = [c1 - c0 for c0, c1 in box]
        axis = max(range(3), key=lambda a: (sizes[a], -a))
        c0, c1 = box[axis]
        k0 = k // 2
        mid = c0 + sizes[axis] * k0 // k
        lo, hi = list(box), list(box)
        lo[axis], hi[axis] = (c0, mid), (mid, c1)
        return cut(tuple(lo), k0) + cut(tuple(hi), k - k0)

    whole = tuple((0, int(s) - 1) for s in shape)
    return [Brick(box) for box in cut(whole, int(n))]


@dataclass(frozen=True)
class Piece:
    """The voxels one rank holds.

    Attributes
    ----------
    volume : Volume
        The voxels (the brick's, plus ghost layers where the volume has them).
    offset : tuple of int
        Global voxel index ``(z, y, x)`` of ``volume.data[0, 0, 0]``.
    brick : Brick
        The cells the rank walks.
    geometry : Geometry
        The whole volume's grid.
    """

    volume: Volume
    offset: tuple[int, int, int]
    brick: object
    geometry: object

    @property
    def extent(self) -> list[int]:
        """VTK extent ``[x0, x1, y0, y1, z0, z1]`` (inclusive) of the voxels held."""
        out: list[int] = []
        for axis in (2, 1, 0):
            out += [self.offset[axis], self.offset[axis] + self.volume.data.shape[axis] - 1]
        return out

    def local(self, ranges) -> tuple[slice, ...]:
        """Slices of ``volume.data`` for global half-open voxel ranges ``(z, y, x)``."""
        return tuple(slice(a - o, b - o) for (a, b), o in zip(ranges, self.offset, strict=True))


def piece_of(volume: Volume, brick, ghost: int) -> Piece:
    """Return the piece of a whole volume a rank holds for ``brick`` (tests, threads)."""
    from dvr_perception.rays.bricks import Geometry

    ranges = brick.voxels(volume.data.shape, ghost)
    sl = tuple(slice(a, b) for a, b in ranges)
    part = Volume(np.ascontiguousarray(volume.data[sl]), volume.spacing, volume.origin)
    return Piece(part, tuple(a for a, _ in ranges), brick, Geometry.of(volume))


def _gather_values(comm: Communicator, values: np.ndarray) -> np.ndarray | None:
    """Every rank's 1-D ``values`` concatenated in rank order on rank 0 (None elsewhere)."""
    if comm.size == 1:
        return values
    if comm.rank != 0:
        comm.send({"v": values}, 0)
        return None
    parts = [values] + [comm.recv(r)["v"] for r in range(1, comm.size)]
    return np.concatenate(parts)


def piece_curvature(comm: Communicator, piece: Piece, spec, sigma: float) -> np.ndarray:
    """``|H|`` on the boundary voxels of the structures, on the piece's voxels (float32).

    Equals :func:`~dvr_perception.rays.curvature.curvature_volume` of the whole volume on the
    voxels the piece's brick reads (its cells' corners) when the piece has
    :func:`ghost_levels` layers; 0 on the other voxels.  Collective (every rank calls it):
    the whole volume's data offset (median of every ``nz // 8``-th slice) is gathered on rank 0
    and broadcast, the largest gradient is a max reduction
    (:func:`~dvr_perception.rays.curvature.curvature_globals` over the voxels each rank
    owns).  Range structures only (a ParaView volume has no label volume).
    """
    from dvr_perception.rays.curvature import (
        CurvatureGlobals,
        curvature_globals,
        curvature_volume,
    )

    if any(s.label is not None for s in spec.structures):
        raise DVRInputError("MPI ranks: label structures are not supported (range structures)")
    shape = piece.geometry.shape
    owned = owned_voxels(piece.brick, shape)
    own = piece.local(owned)
    step = max(1, shape[0] // 8)
    (z0, z1), _, _ = owned
    local = [z - piece.offset[0] for z in range(-(-z0 // step) * step, z1, step)]
    data = piece.volume.data
    mine = (
        data[local][:, own[1], own[2]].astype(np.float32).reshape(-1)
        if local
        else np.zeros(0, np.float32)
    )
    every = _gather_values(comm, mine)
    med = np.float32(np.median(every)) if comm.rank == 0 else None
    got = comm.broadcast({"m": np.asarray([med], np.float32)} if comm.rank == 0 else None)
    mine_globals = curvature_globals(
        piece.volume, spec, sigma=sigma, extent=tuple((o.start, o.stop) for o in own)
    )
    top = mine_globals.gradient_max
    gmax = comm.allreduce_max([-1.0 if top is None else float(top)])[0]
    globals_ = CurvatureGlobals(float(sigma), float(got["m"][0]), None if gmax < 0 else gmax)
    need = piece.local(piece.brick.voxels(shape, 0))  # the corners of the brick's cells
    out = np.zeros(data.shape, np.float32)
    out[need] = curvature_volume(
        piece.volume, spec, sigma=sigma, extent=tuple((o.start, o.stop) for o in need),
        gradient_max=globals_,
    )[0]  # fmt: skip
    return out


def analyze_ranks(comm: Communicator, piece: Piece, spec, camera, *, sigma: float | None = 1.0):
    """Analyse the rays through the whole volume from every rank's piece (collective).

    Parameters
    ----------
    comm : Communicator
        The ranks.
    piece : Piece
        This rank's voxels, with :func:`ghost_levels` ``(spacing, sigma)`` layers.
    spec, camera
        The same on every rank.
    sigma : float or None
        Curvature scale; ``None``: no curvature (E_s without the shape term's curvature).

    Returns
    -------
    analysis : RayAnalysis or None
        On rank 0; ``None`` on the others.
    records : list of dict or None
        On rank 0, one per rank in rank order: ``rank``, ``extent`` (VTK, of the voxels held),
        ``voxels``, ``cells`` (of its brick), ``peak_rss_mb``, ``seconds`` (its part: curvature
        and walk), ``order`` (its place in the view order); ``None`` on the others.
    """
    from dvr_perception.rays import bricks

    t0 = time.perf_counter()
    lo, hi = piece.volume.scalar_range
    scalar_range = comm.allreduce_min_max(lo, hi)
    curv = None if sigma is None else piece_curvature(comm, piece, spec, sigma)
    state = bricks.RayState.start(piece.geometry, spec, camera, scalar_range=scalar_range)
    cells = comm.allgather([list(c) for c in piece.brick.cells])
    order = bricks.view_order([bricks.Brick(tuple(tuple(c) for c in b)) for b in cells], state)
    place = order.index(comm.rank)
    t_wait = time.perf_counter()
    if place > 0:
        state.load(comm.recv(order[place - 1]))
    waited = time.perf_counter() - t_wait
    bricks.walk(
        state, piece.volume, piece.brick, offset=piece.offset, curvature=curv, build_cache=False
    )
    if place < comm.size - 1:
        comm.send(state.arrays(), order[place + 1])
    elif comm.rank != 0:
        comm.send(state.arrays(), 0)
    if comm.rank == 0 and place < comm.size - 1:
        state.load(comm.recv(order[-1]))
    record = {
        "rank": comm.rank,
        "extent": piece.extent,
        "voxels": int(piece.volume.data.size),
        "cells": [list(c) for c in piece.brick.cells],
        "order": place,
        "seconds": round(time.perf_counter() - t0 - waited, 3),
        "peak_rss_mb": peak_rss_mb(),
    }
    records = comm.gather(record)
    if comm.rank != 0:
        return None, None
    return bricks.finish(state, seconds=time.perf_counter() - t0), records


def _run_threads(rank, group, bricks, out: dict):
    """Run ``rank(comm, brick)`` per rank in a thread; re-raise a rank's error; ``out[0]``."""
    threads = [
        threading.Thread(target=rank, args=(c, b)) for c, b in zip(group, bricks, strict=True)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for r in range(len(threads)):
        if isinstance(out.get(r), BaseException):
            raise out[r]
    return out[0]


def analyze_in_threads(volume: Volume, spec, camera, n: int, *, sigma: float | None = 1.0):
    """:func:`analyze_ranks` with ``n`` ranks as threads of this process (tests, checks).

    Returns rank 0's ``(analysis, records)``.
    """
    from dvr_perception.parallel import local_group

    ghost = ghost_levels(volume.spacing, sigma)
    group = local_group(n)
    out: dict = {}

    def rank(comm, brick):
        try:
            out[comm.rank] = analyze_ranks(
                comm, piece_of(volume, brick, ghost), spec, camera, sigma=sigma
            )
        except BaseException as exc:  # re-raised below (a thread would swallow it)
            out[comm.rank] = exc

    return _run_threads(rank, group, block_split(volume.data.shape, n), out)


#: The MPI driver's names, moved to :mod:`dvr_perception.distributed` (deprecated aliases).
_MOVED = ("RankCache", "RankSession", "optimize_in_threads", "warm_up")


def __getattr__(name: str):
    if name in _MOVED:
        import warnings

        warnings.warn(
            f"dvr_perception.rays.ranks.{name} is deprecated; use "
            f"dvr_perception.distributed.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        from dvr_perception import distributed  # layering: deprecated alias

        return getattr(distributed, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
