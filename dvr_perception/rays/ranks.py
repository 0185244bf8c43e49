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
    "RankCache",
    "RankSession",
    "analyze_in_threads",
    "analyze_ranks",
    "block_split",
    "ghost_levels",
    "optimize_in_threads",
    "owned_voxels",
    "piece_curvature",
    "piece_of",
    "warm_up",
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


def warm_up(*, optimize: bool = False) -> None:
    """Compile the kernels a rank runs, once, in this process (numba caches them on disk).

    ``mpiexec -n N`` starts N processes that would otherwise compile the same kernels at the
    same time on a cold cache; worse, a kernel first needed by one rank in the middle of the
    walk is compiled while the others wait (a minute on a loaded core: the "4 ranks spin for
    minutes" of issue 17 was the brick walk of a 16-bit table index, which the phantom never
    needed).  ``dvr-perception pvbatch --ranks N`` calls this in one process first.  Covers 8-
    and 16-bit volumes with a table index of one and of two bytes, shaded and unshaded;
    ``optimize`` also the re-evaluation and opacity kernels of :class:`RankSession`.
    """
    from dataclasses import replace

    from dvr_perception.measures import all_measures
    from dvr_perception.rays.camera import Camera
    from dvr_perception.structures.phantom import make_phantom

    vol, spec = make_phantom(size=16)
    cam = Camera.from_view(vol.bounds, width=8, height=8)
    flat = replace(spec, rendering=replace(spec.rendering, shade=False))
    wide = vol.data.astype(np.uint16) * np.uint16(200)  # a two-byte table index
    for data, s in ((vol.data, spec), (wide, spec), (vol.data, flat)):
        got, _ = analyze_in_threads(Volume(data, vol.spacing, vol.origin), s, cam, 2)
        all_measures(got, s)
    if optimize:
        for data in (vol.data, wide):
            optimize_in_threads(Volume(data, vol.spacing, vol.origin), spec, cam, 2,
                                max_iter=1, resolution=8)  # fmt: skip


# -- the optimiser over ranks ---------------------------------------------------------------------
#: Commands rank 0 broadcasts to the ranks of a :class:`RankSession`.
OP_STOP, OP_ANALYZE, OP_REEVALUATE, OP_OPACITY = 0, 1, 2, 3


def _in_view_order(comm: Communicator, order, fresh, work):
    """Run ``work(state) -> state`` on every rank in view ``order``, handing the state on.

    The first rank in the order starts from ``fresh()``; the last one sends its state to rank
    0, which returns it (the other ranks return ``None``).
    """
    place = order.index(comm.rank)
    state = fresh() if place == 0 else comm.recv(order[place - 1])
    state = work(state)
    if place < comm.size - 1:
        comm.send(state, order[place + 1])
    elif comm.rank != 0:
        comm.send(state, 0)
    if comm.rank != 0:
        return None
    return comm.recv(order[-1]) if place < comm.size - 1 else state


class RankSession:
    """Every rank's part of an optimisation over MPI ranks: its piece and its bricks' caches.

    Made on every rank together (collective: the scalar range and the piece's curvature,
    :func:`piece_curvature`).  Rank 0 runs the optimiser with :meth:`analyze` as its
    ``analyzer`` (:func:`~dvr_perception.optimize.optimize`); the other ranks call
    :meth:`serve`, which carries out what rank 0 broadcasts until :meth:`stop`:

    * ``analyze`` (a camera): every rank walks its brick in view order, handing the rays' state
      on (:func:`~dvr_perception.rays.bricks.walk`), and keeps its brick's cache entries
      (with the normal codes, for a new light); rank 0 finishes the analysis and gets a
      :class:`RankCache` as its cache;
    * ``reevaluate`` (opacities, materials, colours, light): every rank re-composites its
      brick's entries continuing the state of the bricks in front
      (:func:`~dvr_perception.rays._numba_bricks.composite_part`), rank 0 finishes;
    * ``opacity`` (opacities, selected rays): the same for the opacity stage's exact ``E_v``
      gradients (:func:`~dvr_perception.optimize._exact.composite_grad_part`).

    Every result equals the serial one bit for bit: the entries are the whole walk's, in the
    same order, with the same operations.  No rank holds more than its piece.
    """

    def __init__(self, comm: Communicator, piece: Piece, spec, *, sigma: float | None = 1.0):
        from dvr_perception.rays import bricks

        t0 = time.perf_counter()
        self.comm, self.piece, self.spec = comm, piece, spec
        lo, hi = piece.volume.scalar_range
        self.scalar_range = comm.allreduce_min_max(lo, hi)
        self.curvature = None if sigma is None else piece_curvature(comm, piece, spec, sigma)
        cells = comm.allgather([list(c) for c in piece.brick.cells])
        self.bricks = [bricks.Brick(tuple(tuple(c) for c in b)) for b in cells]
        self.views: list[dict] = []
        self.caches: list = []  # rank 0: the RankCache of every view, in order
        self.evaluations = 0
        self.seconds = time.perf_counter() - t0
        self.stopped = False

    # -- rank 0 ---------------------------------------------------------------------------------
    def _command(self, op: int, **arrays) -> None:
        if self.comm.rank != 0:
            raise DVRInputError(f"RankSession: rank {self.comm.rank} cannot give commands")
        if self.stopped:
            raise DVRInputError("RankSession: stopped")
        self.comm.broadcast({"op": np.array([op], np.int64), **arrays})

    def analyze(self, camera):
        """Return the analysis of ``camera`` over every rank (rank 0; the optimiser's analyzer).

        Its ``cache`` is a :class:`RankCache`.
        """
        import json

        text = json.dumps(camera.to_dict()).encode()
        self._command(OP_ANALYZE, camera=np.frombuffer(text, np.uint8))
        return self._analyze(camera)

    def stop(self) -> list | None:
        """End :meth:`serve` on the other ranks (rank 0; collective with them).

        Returns every rank's record (rank order) on rank 0: ``rank``, ``extent``, ``voxels``,
        ``cells``, ``order`` (its place in the first view's order), ``views``,
        ``evaluations``, ``seconds`` (its own work, not the waiting) and ``peak_rss_mb``.
        """
        if self.comm.rank == 0 and not self.stopped:
            self._command(OP_STOP)
        self.stopped = True
        first = self.views[0] if self.views else None
        record = {
            "rank": self.comm.rank,
            "extent": self.piece.extent,
            "voxels": int(self.piece.volume.data.size),
            "cells": [list(c) for c in self.piece.brick.cells],
            "order": None if first is None else first["order"].index(self.comm.rank),
            "views": len(self.views),
            "evaluations": self.evaluations,
            "seconds": round(self.seconds, 3),
            "peak_rss_mb": peak_rss_mb(),
        }
        return self.comm.gather(record)

    # -- the other ranks ------------------------------------------------------------------------
    def serve(self) -> list | None:
        """Carry out rank 0's commands until it stops (ranks other than 0); see :meth:`stop`."""
        import json

        from dvr_perception.rays.camera import Camera

        while True:
            got = self.comm.broadcast(None)
            op = int(got["op"][0])
            if op == OP_STOP:
                self.stopped = True
                return self.stop()
            if op == OP_ANALYZE:
                cam = Camera.from_dict(json.loads(got["camera"].tobytes().decode()))
                self._analyze(cam)
            elif op == OP_REEVALUATE:
                self._reevaluate(int(got["view"][0]), got["opacities"], got["lighting"],
                                 got["colors"], got["light"])  # fmt: skip
            elif op == OP_OPACITY:
                self._opacity(int(got["view"][0]), got["rays"], got["opacities"],
                              bool(got["grad"][0]))  # fmt: skip
            else:
                raise DVRInputError(f"RankSession: unknown command {op} from rank 0")

    # -- every rank -----------------------------------------------------------------------------
    def _timed(self, work):
        """``work`` timed into :attr:`seconds` (a rank's own work, not its waiting)."""

        def timed(arrays):
            t0 = time.perf_counter()
            try:
                return work(arrays)
            finally:
                self.seconds += time.perf_counter() - t0

        return timed

    def _analyze(self, camera):
        from dataclasses import replace

        from dvr_perception.rays import _tables, bricks
        from dvr_perception.rays._results import engine_made

        comm, piece = self.comm, self.piece
        t0 = time.perf_counter()
        state = bricks.RayState.start(
            piece.geometry, self.spec, camera, scalar_range=self.scalar_range
        )
        order = bricks.view_order(self.bricks, state)
        shade = state.tables["shade"]
        k = len(self.spec.structures)
        view = {"state": state, "order": order, "cache": None}
        view["key"] = _tables.shading_key(state.tables["light"], k) if shade else b""
        self.seconds += time.perf_counter() - t0

        def walk(arrays):
            if arrays is not None:
                state.load(arrays)
            view["cache"] = bricks.walk(
                state, piece.volume, piece.brick, offset=piece.offset, curvature=self.curvature,
                build_cache=True, keep_codes=shade,
            )  # fmt: skip
            return state.arrays()

        out = _in_view_order(comm, order, lambda: None, self._timed(walk))
        self.views.append(view)
        if comm.rank != 0:
            return None
        state.load(out)
        analysis = bricks.finish(state)
        for name in ("st", "vis", "asg"):  # the walk's state is no longer needed
            setattr(state, name, np.zeros((0,) * getattr(state, name).ndim))
        cache = RankCache(self, len(self.views) - 1, analysis, state)
        self.caches.append(cache)
        out = replace(analysis, cache=cache)
        engine_made(out, mark=True)
        return out

    def _tables_of(self, view, opacities, lighting, colors, light_dir):
        """Return the view's colour, light and opacity tables (re-shading for a new light)."""
        from dvr_perception.rays import _tables, bricks
        from dvr_perception.structures.spec import Lighting

        state, cache = view["state"], view["cache"]
        spec, t = self.spec, state.tables
        k = len(spec.structures)
        ops = _tables.check_opacities(opacities, k)
        mats = [Lighting(*(float(v) for v in row)) for row in np.asarray(lighting, float)]
        cols, mats = _tables.material(spec, colors=np.asarray(colors, float), lighting=mats)
        light = _tables.light_array(state.camera, mats, np.asarray(light_dir, float),
                                    spec.rendering.light_intensity)  # fmt: skip
        if t["shade"]:
            key = _tables.shading_key(light, k)
            if key != view["key"]:
                nk, nb = bricks._kernels()
                tab = _tables.shading_table(light, k)
                nk.invalidate(cache.shading)
                seg = state.seg
                gz, gy, gx = state.geometry.shape
                off = cache.offset
                geo = np.array([gx, gy, gz, off[2], off[1], off[0]], np.int64)
                j0, j1 = bricks._runs(state, cache.brick)
                nb.fill_range(cache.start, cache.count, cache.lut, cache.steps, cache.shading,
                              cache.curvature, seg["a"], seg["b"], seg["t"], t["step"], j0, j1,
                              cache.codes, np.zeros((2, 2, 2), np.float32), geo, t["ids"], tab,
                              True, False, np.uint32(0))  # fmt: skip
                view["key"] = key
        alpha = _tables.alpha_table(t["ids"], t["memb"], ops, t["ratio"])
        return cols, light, alpha

    def _reevaluate(self, v, opacities, lighting, colors, light_dir):
        from dvr_perception.rays import _tables, bricks

        view = self.views[v]
        cache, state = view["cache"], view["state"]
        nrays = len(state.seg["n"])
        k = len(self.spec.structures)
        has_curv = cache.curvature.size > 0
        _, nb = bricks._kernels()

        def fresh():
            st = np.zeros((nrays, 6))
            st[:, 3] = 1.0
            return {"st": st, "vis": np.zeros((k, nrays))}

        def work(arrays):
            cols, light, alpha = self._tables_of(view, opacities, lighting, colors, light_dir)
            nb.composite_part(cache.start, cache.count, cache.lut, cache.shading,
                              cache.curvature, state.tables["ids"], alpha, cols, light,
                              state.tables["shade"], has_curv, _tables.ERT, arrays["st"],
                              arrays["vis"])  # fmt: skip
            return arrays

        out = _in_view_order(self.comm, view["order"], fresh, self._timed(work))
        self.evaluations += 1
        return out

    def _opacity(self, v, rays, opacities, grad: bool):
        from dvr_perception.optimize._exact import composite_grad_part, opacity_tables
        from dvr_perception.rays import _tables

        view = self.views[v]
        cache, t = view["cache"], view["state"].tables
        k = len(self.spec.structures)
        ops = np.clip(np.asarray(opacities, np.float64), 0.0, 1.0)
        rays = np.ascontiguousarray(rays, np.int64)
        n = rays.size

        def fresh():
            m = n if grad else 1
            return {"tr": np.ones(n), "g": np.zeros((k, n)), "vis": np.zeros((k, n)),
                    "dvis": np.zeros((k, k, m))}  # fmt: skip

        def work(a):
            alpha, dalpha, ids = opacity_tables(t["ids"], t["memb"], t["ratio"], ops)
            composite_grad_part(rays, cache.start, cache.count, cache.lut, ids, alpha, dalpha,
                                k, _tables.ERT, grad, a["tr"], a["g"], a["vis"],
                                a["dvis"])  # fmt: skip
            return a

        out = _in_view_order(self.comm, view["order"], fresh, self._timed(work))
        self.evaluations += 1
        return out


class RankCache:
    """Rank 0's stand-in for the :class:`~dvr_perception.rays.engine.RayCache` of a view.

    The entries live on the ranks (each its brick's); :meth:`reevaluate` and
    :meth:`opacity_pass` broadcast the parameters and gather the composited rays.  Holds what
    the optimiser reads of a cache without its entries: ``spec``, ``camera``, ``ids``,
    ``membership``, ``ratio``, ``assigned``, ``present``, ``importance_accumulated``.
    """

    backend = "numba"

    def __init__(self, session: RankSession, view: int, analysis, state) -> None:
        t = state.tables
        self.session, self.view = session, view
        self.spec, self.camera = session.spec, state.camera
        self.ids, self.membership, self.ratio = t["ids"], t["memb"], t["ratio"]
        self.assigned = analysis.assigned
        self.present = analysis.present
        self.importance_accumulated = analysis.importance_accumulated
        self.stats = dict(analysis.stats)

    def reevaluate(self, *, opacities=None, lighting=None, colors=None, light_direction=None):
        """:func:`~dvr_perception.rays.engine.reevaluate` over the ranks (same parameters)."""
        from dvr_perception.rays import _tables
        from dvr_perception.rays.engine import _finish, _params

        t0 = time.perf_counter()
        spec = self.spec
        s = spec.structures
        k = len(s)
        ops = _tables.check_opacities([x.render_opacity for x in s] if opacities is None
                                      else opacities, k)  # fmt: skip
        mats = [x.lighting for x in s] if lighting is None else list(lighting)
        cols = np.array([x.color for x in s], float) if colors is None else colors
        cols_checked, mats = _tables.material(spec, colors=cols, lighting=mats)
        direction = spec.rendering.light_direction if light_direction is None else light_direction
        arrays = {
            "view": np.array([self.view], np.int64),
            "opacities": ops,
            "lighting": np.array(
                [[m.ambient, m.diffuse, m.specular, m.specular_power] for m in mats], float
            ),
            "colors": np.asarray(cols, float),
            "light": np.asarray(direction, np.float64).reshape(-1),
        }
        self.session._command(OP_REEVALUATE, **arrays)
        got = self.session._reevaluate(self.view, ops, arrays["lighting"], arrays["colors"],
                                       arrays["light"])  # fmt: skip
        st, vis = got["st"], got["vis"]
        rgba = np.empty((len(st), 4))
        np.minimum(st[:, :3], 1.0, out=rgba[:, :3])
        rgba[:, 3] = 1.0 - st[:, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            cimg = np.where(st[:, 5] > 0.0, st[:, 4] / np.where(st[:, 5] > 0, st[:, 5], 1.0), 0.0)
        stats = {"backend": "numba", "rays": len(st), "reevaluated": True,
                 "ranks": self.session.comm.size}  # fmt: skip
        stats["params"] = _params(ops, cols_checked, mats, direction)
        out = _finish(rgba, np.ascontiguousarray(vis), self.assigned, self.present, cimg, spec,
                      self.camera, stats, self, self.importance_accumulated)  # fmt: skip
        stats["seconds"] = time.perf_counter() - t0
        return out

    def opacity_pass(self, rays, ops, grad: bool) -> tuple:
        """``(vis, dvis, acc, dacc)`` of the selected rays at opacities ``ops`` over the ranks.

        As :class:`~dvr_perception.optimize._exact.OpacityModel` computes them from a whole
        cache (``dvis`` and ``dacc`` are zeros of one ray without ``grad``).
        """
        rays = np.ascontiguousarray(rays, np.int64)
        ops = np.asarray(ops, np.float64)
        self.session._command(OP_OPACITY, view=np.array([self.view], np.int64), rays=rays,
                              opacities=ops, grad=np.array([int(grad)], np.int64))  # fmt: skip
        got = self.session._opacity(self.view, rays, ops, grad)
        tr, g = got["tr"], got["g"]
        dacc = -tr[None, :] * g if grad else np.zeros((len(g), 1))
        return got["vis"], got["dvis"], 1.0 - tr, dacc


def optimize_in_threads(volume: Volume, spec, camera, n: int, **options):
    """:func:`~dvr_perception.optimize.optimize` over ``n`` ranks as threads (tests, checks).

    Returns rank 0's ``(result, records)`` (:meth:`RankSession.stop`).
    """
    from dvr_perception.optimize import optimize
    from dvr_perception.parallel import local_group

    ghost = ghost_levels(volume.spacing, 1.0)
    group = local_group(n)
    out: dict = {}

    def rank(comm, brick):
        try:
            session = RankSession(comm, piece_of(volume, brick, ghost), spec)
            if comm.rank != 0:
                out[comm.rank] = session.serve()
                return
            try:
                res = optimize(None, spec, camera, analyzer=session.analyze, **options)
            finally:
                records = session.stop()
            out[0] = (res, records)
        except BaseException as exc:  # re-raised below (a thread would swallow it)
            out[comm.rank] = exc

    return _run_threads(rank, group, block_split(volume.data.shape, n), out)
