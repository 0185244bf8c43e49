"""The optimiser over MPI ranks, each holding one piece of the volume (the MPI driver).

Built on the ray-level pieces and walk of :mod:`dvr_perception.rays.ranks`
(:func:`~dvr_perception.rays.ranks.analyze_ranks` for one analysis):
:class:`RankSession` keeps every rank's brick caches across the optimiser's evaluations, rank 0
runs :func:`~dvr_perception.optimize.optimize` with :meth:`RankSession.analyze` as its analyzer
and gets a :class:`RankCache` per view, whose re-evaluations and opacity passes are carried out
by all ranks.  :func:`warm_up` compiles the kernels a rank runs (measures and optimiser
included) once, before ``mpiexec`` starts the ranks.
"""

from __future__ import annotations

import time

import numpy as np

from dvr_perception._deprecation import renamed_keyword
from dvr_perception.errors import DVRInputError
from dvr_perception.parallel import Communicator, peak_rss_mb
from dvr_perception.rays.ranks import (
    Piece,
    _run_threads,
    analyze_in_threads,
    block_split,
    ghost_levels,
    piece_curvature,
    piece_of,
)
from dvr_perception.volume.volume import Volume

__all__ = ["RankCache", "RankSession", "optimize_in_threads", "warm_up"]


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
                                 got["colours"], got["light"])  # fmt: skip
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

    def _tables_of(self, view, opacities, lighting, colours, light_dir):
        """Return the view's colour, light and opacity tables (re-shading for a new light)."""
        from dvr_perception.rays import _tables, bricks
        from dvr_perception.structures.spec import Lighting

        state, cache = view["state"], view["cache"]
        spec, t = self.spec, state.tables
        k = len(spec.structures)
        ops = _tables.check_opacities(opacities, k)
        mats = [Lighting(*(float(v) for v in row)) for row in np.asarray(lighting, float)]
        cols, mats = _tables.material(spec, colours=np.asarray(colours, float), lighting=mats)
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

    def _reevaluate(self, v, opacities, lighting, colours, light_dir):
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
            cols, light, alpha = self._tables_of(view, opacities, lighting, colours, light_dir)
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

    @renamed_keyword("colors", "colours")
    def reevaluate(self, *, opacities=None, lighting=None, colours=None, light_direction=None):
        """:func:`~dvr_perception.rays.engine.reevaluate` over the ranks (same parameters)."""
        from dvr_perception.rays import _tables
        from dvr_perception.rays._walk_setup import _finish, _params

        t0 = time.perf_counter()
        spec = self.spec
        s = spec.structures
        k = len(s)
        ops = _tables.check_opacities([x.render_opacity for x in s] if opacities is None
                                      else opacities, k)  # fmt: skip
        mats = [x.lighting for x in s] if lighting is None else list(lighting)
        cols = np.array([x.colour for x in s], float) if colours is None else colours
        cols_checked, mats = _tables.material(spec, colours=cols, lighting=mats)
        direction = spec.rendering.light_direction if light_direction is None else light_direction
        arrays = {
            "view": np.array([self.view], np.int64),
            "opacities": ops,
            "lighting": np.array(
                [[m.ambient, m.diffuse, m.specular, m.specular_power] for m in mats], float
            ),
            "colours": np.asarray(cols, float),
            "light": np.asarray(direction, np.float64).reshape(-1),
        }
        self.session._command(OP_REEVALUATE, **arrays)
        got = self.session._reevaluate(self.view, ops, arrays["lighting"], arrays["colours"],
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
