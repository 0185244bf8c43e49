"""Bricked ray analysis: the engine's result, computed one box of the volume at a time.

A :class:`Brick` owns a box of the whole volume's cells.  Every ray's samples in a brick are one
run of its sample indices, so walking the bricks in view order and handing each ray's state on
(premultiplied colour, transmittance, the transmittance at the importances, curvature sums,
present bits; visible and assigned opacities add up) reproduces the whole walk sample by sample,
early ray termination included: a bricked analysis equals :func:`~dvr_perception.rays.engine.
analyze` up to float rounding (in practice bit for bit).  Each brick reads only its voxels plus
one ghost layer (the normals' central differences), so the derived volumes (table indices,
normal codes, cell and block maps) exist for one brick at a time.

The pieces are public so that ParaView's MPI ranks can each walk their own piece:

* :class:`Geometry` - the whole volume's grid (no data); :class:`RayState` - every ray's state,
  started with :meth:`RayState.start` and shipped between processes with
  :meth:`RayState.arrays` / :meth:`RayState.load`;
* :func:`split`, :func:`from_piece_extent` and :func:`view_order` - bricks and their order;
* :func:`walk` - one brick (its :class:`BrickCache` for re-evaluation);
* :func:`finish` - the :class:`~dvr_perception.rays.engine.RayAnalysis`, with the bricks'
  caches merged into one :class:`~dvr_perception.rays.engine.RayCache` that
  :func:`~dvr_perception.rays.engine.reevaluate` and the optimiser use as usual.

:func:`analyze_bricked` does all of it in one process.  Needs numba.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from dvr_perception._numba import kernels
from dvr_perception._progress import reporter
from dvr_perception.errors import DVRInputError
from dvr_perception.rays import _grid, _tables, memory
from dvr_perception.rays._results import RayAnalysis, RayCache
from dvr_perception.rays._walk_setup import (
    _check_curvature,
    _check_inputs,
    _finish,
    _group,
    _interleaved,
    _params,
    _plateau_entries,
    _segments,
    _tail_tables,
    ray_order,
    walk_curvature,
)
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.spec import StructureSpec
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.volume import Volume

__all__ = [
    "Brick",
    "BrickCache",
    "Geometry",
    "RayState",
    "analyze_bricked",
    "analyze_bricked_views",
    "finish",
    "from_piece_extent",
    "split",
    "view_order",
    "walk",
]

#: Voxels a brick reads around its cells: the central differences of the normals at its
#: cells' corners.
GHOST = 1


def _kernels():
    nk = kernels("dvr_perception.rays._numba_kernels")
    nb = kernels("dvr_perception.rays._numba_bricks")
    if nk is None or nb is None:
        raise DVRInputError(
            "bricked analysis needs numba (not importable, or DVR_PERCEPTION_NO_NUMBA is set); "
            "analyse the volume whole (no brick size / memory limit)"
        )
    return nk, nb


@dataclass(frozen=True)
class Geometry:
    """The whole volume's grid: what every brick must agree on (no voxel data).

    Parameters
    ----------
    shape : tuple of int
        Voxels ``(z, y, x)``.
    spacing, origin : tuple of float
        As :class:`~dvr_perception.volume.volume.Volume` (x, y, z).
    dtype : numpy.dtype
        The scalar type (the transfer table's layout depends on it).

    Examples
    --------
    >>> g = Geometry((2, 3, 4), (1.0, 1.0, 2.0), (0.0, 0.0, 0.0), np.dtype(np.uint8))
    >>> g.dims, g.bounds
    ((4, 3, 2), (0.0, 3.0, 0.0, 2.0, 0.0, 2.0))
    """

    shape: tuple[int, int, int]
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float]
    dtype: np.dtype

    @classmethod
    def of(cls, volume: Volume) -> Geometry:
        """Return the geometry of ``volume``."""
        return cls(tuple(volume.data.shape), volume.spacing, volume.origin, volume.data.dtype)

    @property
    def dims(self) -> tuple[int, int, int]:
        """Voxels along x, y, z."""
        z, y, x = self.shape
        return (x, y, z)

    @property
    def bounds(self) -> tuple[float, ...]:
        """World bounds of the voxel centres ``(xmin, xmax, ymin, ymax, zmin, zmax)``."""
        out: list[float] = []
        for n, s, o in zip(self.dims, self.spacing, self.origin, strict=True):
            out += [o, o + (n - 1) * s]
        return tuple(out)


@dataclass(frozen=True)
class Brick:
    """A box of cells ``((z0, z1), (y0, y1), (x0, x1))``, half-open.

    Cell ``i`` lies between voxels ``i`` and ``i + 1``; an axis of ``n`` voxels has cells
    ``0 .. n - 2``.

    Examples
    --------
    >>> Brick(((0, 4), (0, 9), (3, 9))).voxels((5, 10, 10))
    ((0, 5), (0, 10), (2, 10))
    """

    cells: tuple[tuple[int, int], tuple[int, int], tuple[int, int]]

    def voxels(self, shape, ghost: int = GHOST) -> tuple[tuple[int, int], ...]:
        """Voxel ranges ``(z, y, x)`` the brick reads: its cells' corners and ``ghost`` more."""
        return tuple(
            (max(c0 - ghost, 0), min(c1 + 1 + ghost, n))
            for (c0, c1), n in zip(self.cells, shape, strict=True)
        )

    @property
    def ncells(self) -> int:
        """Number of cells."""
        return math.prod(c1 - c0 for c0, c1 in self.cells)


def split(shape, cells) -> list[Brick]:
    """Cut a volume of ``shape`` voxels ``(z, y, x)`` into bricks of at most ``cells`` cells.

    Examples
    --------
    >>> [b.cells for b in split((3, 4, 10), (8, 8, 5))]
    [((0, 2), (0, 3), (0, 5)), ((0, 2), (0, 3), (5, 9))]
    """
    try:
        size = tuple(int(c) for c in cells)
    except (TypeError, ValueError):
        size = ()
    if len(size) != 3 or min(size) < 1:
        raise DVRInputError(f"brick: expected three positive cell counts (z, y, x), got {cells!r}")
    edges = [[*range(0, n - 1, s), n - 1] for n, s in zip(shape, size, strict=True)]
    return [
        Brick(((z0, z1), (y0, y1), (x0, x1)))
        for z0, z1 in zip(edges[0][:-1], edges[0][1:], strict=True)
        for y0, y1 in zip(edges[1][:-1], edges[1][1:], strict=True)
        for x0, x1 in zip(edges[2][:-1], edges[2][1:], strict=True)
    ]


def from_piece_extent(extent, whole_extent) -> Brick:
    """Return the brick owning the cells of a VTK piece extent (without ghost levels).

    ``extent`` and ``whole_extent`` are VTK's ``(x0, x1, y0, y1, z0, z1)`` inclusive point
    indices; pieces split by VTK share their boundary planes, so their cells do not overlap.

    Examples
    --------
    >>> from_piece_extent((0, 9, 0, 9, 4, 9), (0, 9, 0, 9, 0, 9)).cells
    ((4, 9), (0, 9), (0, 9))
    """
    e = [int(v) for v in extent]
    w = [int(v) for v in whole_extent]
    cells = []
    for axis in (2, 1, 0):
        lo, hi = e[2 * axis] - w[2 * axis], e[2 * axis + 1] - w[2 * axis]
        cells.append((lo, max(hi, lo)))
    return Brick(tuple(cells))


@dataclass(eq=False)
class BrickCache:
    """One brick's cache entries, rays in row-major order (as :class:`RayCache`'s)."""

    brick: Brick
    start: np.ndarray
    count: np.ndarray
    lut: np.ndarray
    steps: np.ndarray
    shading: np.ndarray
    curvature: np.ndarray
    #: The brick's normal codes (uint16, its piece's voxels) when kept for a change of light.
    codes: np.ndarray | None = None
    offset: tuple = (0, 0, 0)


@dataclass(eq=False)
class RayState:
    """Every ray's state between bricks, with the tables the bricks share.

    ``st`` (R, 7) float64: premultiplied r, g, b, transmittance, transmittance at the
    importances, curvature numerator and weight; ``bits`` (R,) present bits; ``vis`` (K, R)
    and ``asg`` (K + 1, R; the last row counts samples outside every structure) float64.
    ``exact``: walks without the cache walk every sample behind early ray termination (else
    they skip what cannot change a result, as :func:`~dvr_perception.rays.engine.analyze`'s
    ``exact`` says).
    """

    geometry: Geometry
    spec: StructureSpec
    camera: Camera
    opacities: np.ndarray
    occlusion_free: bool
    seg: dict
    tables: dict
    st: np.ndarray
    bits: np.ndarray
    vis: np.ndarray
    asg: np.ndarray
    stats: dict = field(default_factory=dict)
    exact: bool = False

    @classmethod
    def start(cls, geometry, spec, camera, *, scalar_range, opacities=None, occlusion_free=True,
              segments=None, exact=False):  # fmt: skip
        """Fresh rays for ``camera`` through the whole volume ``geometry``.

        ``scalar_range`` must be the whole volume's ``(min, max)`` (the transfer table spans
        it); ``exact``: see the class.  ``segments``: the camera's rays when already made
        (``_walk_setup._segments`` of the same camera, volume and sample distance; read only).
        """
        if not isinstance(geometry, Geometry):
            raise DVRInputError(f"geometry: expected a Geometry, got {type(geometry).__name__}")
        probe = Volume(np.zeros((2, 2, 2), geometry.dtype), geometry.spacing, geometry.origin)
        _check_inputs(probe, spec, camera, "numba")
        nk, _ = _kernels()
        k = len(spec.structures)
        imp = _tables.check_opacities([s.importance for s in spec.structures], k, "importance")
        ops = _tables.check_opacities(
            [s.render_opacity for s in spec.structures] if opacities is None else opacities, k
        )
        step, unit = _tables.step_and_unit(spec, geometry)
        cols, mats = _tables.material(spec)
        rs = spec.rendering
        light = _tables.light_array(camera, mats, rs.light_direction, rs.light_intensity)
        lut = build_lut(spec, scalar_range=tuple(scalar_range), dtype=geometry.dtype)
        lab_s = [i for i, s in enumerate(spec.structures) if s.label is not None]
        ids = np.ascontiguousarray(np.concatenate([lut.ids, np.asarray(lab_s, lut.ids.dtype)]))
        memb = np.ascontiguousarray(
            np.concatenate([lut.membership, np.ones(len(lab_s), lut.membership.dtype)])
        )
        ratio = step / unit
        alpha_w = _tables.alpha_table(ids, memb, imp, ratio)
        shade = bool(rs.shade)
        tables = {
            "lut": lut,
            "labels": tuple(spec.structures[i].label for i in lab_s),
            "ids": ids,
            "memb": memb,
            "ratio": ratio,
            "step": float(step),
            "alpha_w": alpha_w,
            "alpha_r": _tables.alpha_table(ids, memb, ops, ratio),
            "cols": cols,
            "mats": mats,
            "light": light,
            "tab": _tables.shading_table(light, k) if shade else np.zeros((1, 1, 2), np.uint16),
            "shade": shade,
            "rep": _plateau_entries(ids, memb, k),
        }
        tables["tail"] = _tail_tables(ids, memb, alpha_w, tables["rep"], k)
        seg = _segments(nk, camera, geometry, step) if segments is None else segments
        nrays = camera.width * camera.height
        st = np.zeros((nrays, 7))
        st[:, 3:5] = 1.0
        return cls(
            geometry, spec, camera, ops, bool(occlusion_free), seg, tables, st,
            np.zeros(nrays, np.uint32), np.zeros((k, nrays)), np.zeros((k + 1, nrays)),
            {"samples_walked": 0, "bricks": 0, "t_start": time.perf_counter()}, bool(exact),
        )  # fmt: skip

    def arrays(self) -> dict[str, np.ndarray]:
        """Return the per-ray state, to hand to another process."""
        return {"st": self.st, "bits": self.bits, "vis": self.vis, "asg": self.asg}

    def load(self, arrays: dict) -> None:
        """Take over a state from :meth:`arrays` (of the same camera and spec)."""
        for name, mine in self.arrays().items():
            got = np.asarray(arrays[name])
            if got.shape != mine.shape:
                raise DVRInputError(f"state {name!r}: expected shape {mine.shape}, got {got.shape}")
            mine[...] = got


def view_order(bricks, state: RayState) -> list[int]:
    """Return the indices of ``bricks`` front to back: an order every ray meets them in.

    Along each axis a ray moves away from the camera's position (perspective) or in the view
    direction (parallel), so a brick is met only after every brick closer to the camera's
    brick on each axis; ordering by the summed distance in cells respects that for all rays.
    """
    cam, geo = state.camera, state.geometry
    fwd = cam.basis()[0]
    pos = (np.asarray(cam.position, float) - np.asarray(geo.origin)) / np.asarray(geo.spacing)
    keys = []
    for i, br in enumerate(bricks):
        key = 0.0
        for axis in range(3):  # x, y, z
            c0, c1 = br.cells[2 - axis]
            if cam.parallel_projection:
                key += fwd[axis] / geo.spacing[axis] * (c0 + c1) / 2.0
            else:
                p = pos[axis]
                key += max(c0 - p, p - c1, 0.0)
        keys.append((key, i))
    return [i for _, i in sorted(keys)]


def derive(piece: Volume, state: RayState) -> tuple:
    """Return the brick's derived volumes ``(vol, tix, cells, blocks, labmap)`` (:mod:`_grid`).

    ``vol`` is the voxel records (table index and normal code) when shading, else the table
    index; computed on the brick's own voxels.
    """
    t = state.tables
    lut = t["lut"]
    idx = _grid.index_volume(piece, lut.lo, lut.scale, lut.size)
    labmap = _grid.label_map(piece, t["labels"]) if t["labels"] else None
    cells = _grid.cell_map(piece, idx, t["ids"], t["memb"], labmap)
    vol = _grid.voxel_records(piece, idx, cells) if t["shade"] else idx
    return vol, _grid.compact_index(piece, idx), cells, _grid.block_map(piece, cells), labmap


#: A walk without a cache derives a brick's normal codes only where it can shade
#: (:func:`_derive_reached`): computing every code took 55 % of a render of the 1024 x 1024 x
#: 904 CT, whose rays stop at the skin.
REACHED_CODES = True


def _derive_reached(piece: Volume, state: RayState, brick: Brick, offset) -> tuple:
    """:func:`derive` for a walk of ``state`` without a cache, next in view order.

    The normal codes are computed only at the corners of the cells in the blocks where the
    walk can shade (:func:`_numba_bricks.reached_blocks`, from the rays' state before this
    brick); every other voxel's record holds the zero-gradient code, which the walk never
    reads.  Not for a memo (another view shades elsewhere).
    """
    t = state.tables
    lut = t["lut"]
    idx = _grid.index_volume(piece, lut.lo, lut.scale, lut.size)
    labmap = _grid.label_map(piece, t["labels"]) if t["labels"] else None
    cells = _grid.cell_map(piece, idx, t["ids"], t["memb"], labmap)
    blocks = _grid.block_map(piece, cells)
    rec = _reached_records(piece, state, brick, offset, idx, cells, blocks, labmap)
    return rec, _grid.compact_index(piece, idx), cells, blocks, labmap


def _reached_records(piece, state, brick, offset, index, cells, blocks, labmap) -> np.ndarray:
    """Return :func:`_derive_reached`'s voxel records from the brick's other derived volumes.

    ``index``: the table index per voxel (or its compact copy, the same values).
    """
    _, nb = _kernels()
    t, seg = state.tables, state.seg
    lut = t["lut"]
    j0, j1 = _runs(state, brick)
    gz, gy, gx = state.geometry.shape
    geo = np.array([gx, gy, gz, offset[2], offset[1], offset[0]], np.int64)
    lab, lab_base = (labmap, lut.size) if labmap is not None else (np.zeros((2, 2, 2), np.uint8),
                                                                   -1)  # fmt: skip
    mask = np.zeros(blocks.shape, np.bool_)
    nb.reached_blocks(index, cells, blocks, t["rep"], lab, lab_base, t["memb"], t["alpha_r"],
                      seg["a"], seg["b"], seg["t"], j0, j1, t["step"],
                      np.ascontiguousarray(state.st[:, 3]), _tables.ERT, geo, mask)  # fmt: skip
    rec = np.empty(index.shape, np.uint32)
    nb.records_reached(piece.data, _aspect(piece), index, mask, rec)
    return rec


def _aspect(piece: Volume) -> np.ndarray:
    spacing = np.asarray(piece.spacing, float)
    return (2.0 * spacing / spacing.mean()).astype(np.float32)  # as _grid.voxel_records


def _derive_compact(piece: Volume, state: RayState) -> tuple:
    """:func:`derive` without the voxel records: a :class:`_PartialMemo` entry.

    ``(None, tix, cells, blocks, labmap)``: the table index (uint8 where the table allows,
    else the uint16 index), cell classes, block map and labels; about 2 bytes a voxel
    instead of 7.  :func:`_expand` makes the records again from the brick's piece.
    """
    t = state.tables
    lut = t["lut"]
    idx = _grid.index_volume(piece, lut.lo, lut.scale, lut.size)
    labmap = _grid.label_map(piece, t["labels"]) if t["labels"] else None
    cells = _grid.cell_map(piece, idx, t["ids"], t["memb"], labmap)
    return None, _grid.compact_index(piece, idx), cells, _grid.block_map(piece, cells), labmap


def _expand(piece, state, entry, brick, offset, reached) -> tuple:
    """:func:`derive`'s volumes from a :func:`_derive_compact` entry and the brick's ``piece``.

    The records are made from the kept table index and cell classes (:func:`derive`'s,
    bit for bit): for a walk without a cache (``reached``) only where it can shade
    (:func:`_reached_records`), else wherever shading can read them.
    """
    _, tix, cells, blocks, labmap = entry
    if reached:
        rec = _reached_records(piece, state, brick, offset, tix, cells, blocks, labmap)
    else:
        rec = np.empty(tix.shape, np.uint32)
        _grid._fast().records_where(piece.data, _aspect(piece), tix, cells, rec)
    return rec, tix, cells, blocks, labmap


def _records(piece: Volume, state: RayState) -> np.ndarray:
    """Return the brick's voxel records only (:func:`derive`'s first, when shading)."""
    t = state.tables
    lut = t["lut"]
    idx = _grid.index_volume(piece, lut.lo, lut.scale, lut.size)
    labmap = _grid.label_map(piece, t["labels"]) if t["labels"] else None
    cells = _grid.cell_map(piece, idx, t["ids"], t["memb"], labmap)
    return _grid.voxel_records(piece, idx, cells)


def _piece_arrays(piece: Volume, state: RayState, curvature, derived=None, skip=False):
    """Per-brick arrays the walk reads: ``vol``, the ``maps`` tuple and the curvature.

    ``skip``: the skipping walk behind early ray termination (``_grid.skip_maps``; its block
    masks are memoised on ``piece``).
    """
    t = state.tables
    vol, tix, cells, blocks, labmap = derive(piece, state) if derived is None else derived
    size = t["lut"].size
    lab = (labmap, size) if labmap is not None else (np.zeros((2, 2, 2), np.uint8), -1)
    sm = _grid.skip_maps(piece, tix, t["tail"][3], labmap, lab[1], skip, len(t["rep"]))
    occ = _grid.block_occupancy(piece, cells)
    maps = (tix, cells, blocks, occ, t["rep"], *lab, *t["tail"], *sm)
    cv = np.zeros((2, 2, 2), np.float32) if curvature is None else curvature
    return vol, maps, cv


def _check_piece(piece, brick, offset, state, curvature):
    if piece is None:  # derived volumes given: only the offset is needed
        return tuple(int(o) for o in offset)
    if not isinstance(piece, Volume):
        raise DVRInputError(f"piece: expected a Volume, got {type(piece).__name__}")
    if not isinstance(brick, Brick):
        raise DVRInputError(f"brick: expected a Brick, got {type(brick).__name__}")
    off = tuple(int(o) for o in offset)
    need = brick.voxels(state.geometry.shape)
    for axis, ((v0, v1), o, n) in enumerate(zip(need, off, piece.data.shape, strict=True)):
        if v0 < o or v1 > o + n:
            raise DVRInputError(
                f"piece: axis {'zyx'[axis]} holds voxels {o}..{o + n - 1}, but brick "
                f"{brick.cells} needs {v0}..{v1 - 1} (its cells and {GHOST} ghost layer)"
            )
    if curvature is not None:
        c = np.asarray(curvature)
        if c.shape != piece.data.shape or c.dtype != np.float32:
            raise DVRInputError(
                f"curvature: expected float32 of the piece's shape {piece.data.shape}, "
                f"got {c.dtype} {c.shape}"
            )
    return off


#: Keep the bricks' sample runs (for re-shading after a change of light, and for the next
#: analyses of the same camera and bricks) up to this many bytes.
RUNS_BYTES = memory.RUNS_BYTES
#: Runs of recent analyses: (camera pack, volume shape, brick) -> (j0, j1), oldest first.
_RUNS: dict = {}
_RUNS_LOCK = threading.Lock()


def _runs(state: RayState, brick: Brick) -> tuple[np.ndarray, np.ndarray]:
    """Every ray's run ``[j0, j1)`` of samples in ``brick`` (not to be changed; kept while small).

    The runs depend on the rays and the brick only: analyses of the same camera and bricks
    (a measure per view, the optimiser's analyses) find them here.
    """
    seg = state.seg
    key = state.stats.get("rays_key")
    if key is None:
        pack = _grid.camera_pack(state.camera, state.geometry, state.tables["step"])
        key = state.stats["rays_key"] = (pack.tobytes(), state.geometry.shape)
    with _RUNS_LOCK:
        hit = _RUNS.pop((key, brick), None)
        if hit is not None:
            _RUNS[(key, brick)] = hit  # the most recent last
            return hit
    _, nb = _kernels()
    gz, gy, gx = state.geometry.shape
    lo = np.array([c[0] for c in brick.cells[::-1]], np.int64)
    hi = np.array([c[1] for c in brick.cells[::-1]], np.int64)
    nrays = len(seg["n"])
    j0 = np.empty(nrays, np.int64)
    j1 = np.empty(nrays, np.int64)
    nb.brick_ranges(seg["a"], seg["b"], seg["t"], seg["n"], state.tables["step"], lo, hi,
                    np.array([gx, gy, gz], np.int64), j0, j1)  # fmt: skip
    if 16 * nrays <= RUNS_BYTES:
        with _RUNS_LOCK:
            _RUNS[(key, brick)] = (j0, j1)
            while sum(a.nbytes + b.nbytes for a, b in _RUNS.values()) > RUNS_BYTES:
                del _RUNS[next(iter(_RUNS))]
    return j0, j1


def walk(state: RayState, piece: Volume, brick: Brick, *, offset=(0, 0, 0), curvature=None,
         build_cache: bool = True, keep_codes: bool = False, derived=None,
         progress=None, shade_all: bool = True, curvature_all: bool = True,
         arena=None) -> BrickCache | None:  # fmt: skip
    """Walk ``brick``'s samples of every ray, continuing ``state`` (changed in place).

    Parameters
    ----------
    state : RayState
        Every ray's state after the bricks in front of this one (:func:`view_order`).
    piece : Volume
        Voxels holding the brick and its ghost layer (:meth:`Brick.voxels`); the whole volume
        is fine too.
    brick : Brick
        The cells to walk.
    offset : tuple of int
        Global voxel index ``(z, y, x)`` of ``piece.data[0, 0, 0]``.
    curvature : numpy.ndarray, optional
        float32 ``|H|`` on ``piece``'s voxels (see :func:`~dvr_perception.rays.engine.analyze`).
    build_cache : bool
        Return the brick's cache entries, shading and curvature computed for every entry.
    keep_codes : bool
        Keep the brick's normal codes in its cache (2 bytes per voxel): a change of light
        then re-shades from them instead of re-reading the volume.
    derived : tuple, optional
        The brick's derived volumes from an earlier walk (:func:`derive`); ``piece`` is then
        only checked, not read.
    progress : callable, optional
        Called with the fraction of the brick's rays walked (a float in [0, 1], reaching 1.0)
        after each group of ray tiles: the rays then go to the kernel in groups of chunks, one
        call each, with the same result.  :class:`StopIteration` from it raises
        :class:`~dvr_perception.errors.DVRCancelled` (the state is then partly walked).
    shade_all : bool
        Shade every cache entry (default).  False: only the entries composited here; the
        others stay unset for a lazily shaded cache (:func:`_filler`), which must shade
        whatever compositing can reach before it composites.
    curvature_all : bool
        The same for the entries' curvature (False only with ``shade_all`` False: the
        shading's marker is the one compositing tests).
    arena : _Arena, optional
        Where the brick's cache entries go (until the bricks' caches are merged); default
        fresh arrays.

    Returns
    -------
    BrickCache or None
    """
    _kernels()  # one clear error without numba
    report = reporter(progress)
    off = _check_piece(piece, brick, offset, state, curvature)
    if build_cache and not state.occlusion_free:
        raise DVRInputError("build_cache: needs an occlusion-free state (occlusion_free=True)")
    cam = state.camera
    j0, j1 = _runs(state, brick)
    skip = state.occlusion_free and not build_cache and not state.exact
    vol, maps, cv = _piece_arrays(piece, state, curvature, derived, skip)
    if skip:
        state.stats["assigned_cap"] = _grid.SATURATION
    order, chunk_ptr = ray_order(cam.height, cam.width)
    if report:
        order, chunk_ptr = _interleaved(order, chunk_ptr, _group())
    order, chunk_ptr, per_chunk = _crossing(order, chunk_ptr, j0, j1)
    nchunk = len(chunk_ptr) - 1
    if not build_cache:
        per_chunk = np.zeros(nchunk, np.int64)
    chunk_base = np.zeros(nchunk, np.int64)
    np.cumsum(per_chunk[:-1], out=chunk_base[1:])
    cap = max(int(per_chunk.sum()), 1)
    mine = build_cache and _SRC_LOCK.acquire(blocking=False)
    try:
        return _walk_src(state, brick, vol, maps, cv if curvature is not None else None, j0, j1,
                         order, chunk_ptr, chunk_base, cap, off, report, build_cache, keep_codes,
                         shade_all, curvature_all, mine, arena)  # fmt: skip
    finally:
        if mine:
            _SRC_LOCK.release()


def _crossing(order, chunk_ptr, j0, j1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the rays of ``order``'s chunks that cross the brick (``j1 > j0``), chunk by chunk.

    Empty chunks are dropped; each keeps its rays in their order, so the walk visits only the
    brick's rays and its threads share them as they share the image's tiles; every ray's
    result is the same (each ray is computed on its own).  Also each kept chunk's samples in
    the brick.  One pass (:func:`_numba_bricks.crossing`; numpy's took 3 ms a brick at 512^2).

    Examples
    --------
    >>> order, ptr = np.array([3, 0, 1, 2]), np.array([0, 2, 4])
    >>> o, p, runs = _crossing(order, ptr, np.zeros(4, int), np.array([0, 1, 0, 0]))
    >>> o.tolist(), p.tolist(), runs.tolist()
    ([1], [0, 1], [1])
    """
    _, nb = _kernels()
    out = np.empty(len(order), np.int64)
    ptr = np.empty(len(chunk_ptr), np.int64)
    runs = np.empty(max(len(chunk_ptr) - 1, 0), np.int64)
    i64 = np.int64
    m, nc = nb.crossing(np.asarray(order, i64), np.asarray(chunk_ptr, i64), np.asarray(j0, i64),
                        np.asarray(j1, i64), out, ptr, runs)  # fmt: skip
    return out[:m], ptr[: nc + 1], runs[:nc]


#: The walk's entries before compaction, reused from brick to brick (fresh memory costs page
#: faults), and their lock (an analysis in another thread uses fresh arrays).
_SRC: dict = {}
_SRC_LOCK = threading.Lock()


def _src(name, n, tail, dtype, shared):
    """``n`` rows of the reused scratch ``name`` (``shared``), else a fresh array."""
    if not shared:
        return np.empty((n, *tail), dtype)
    a = _SRC.get(name)
    if a is None or len(a) < n:
        a = np.empty((max(n, int(1.25 * len(a)) if a is not None else n), *tail), dtype)
        _SRC[name] = a
    return a[:n]


def _walk_src(state, brick, vol, maps, cv, j0, j1, order, chunk_ptr, chunk_base, cap, off,
              report, build_cache, keep_codes, shade_all, curvature_all, shared,
              arena=None):  # fmt: skip
    """:func:`walk` once the runs and chunks are known (``shared``: the scratch is ours)."""
    nk, nb = _kernels()
    t, seg, cam = state.tables, state.seg, state.camera
    gz, gy, gx = state.geometry.shape
    nrays = cam.width * cam.height
    nchunk = len(chunk_ptr) - 1
    has_curv = cv is not None
    shade = t["shade"]
    cv = np.zeros((2, 2, 2), np.float32) if cv is None else cv
    src = (
        _src("lut", cap, (), np.uint16, shared),
        _src("j", cap, (), np.int32, shared),
        _src("sh", cap if shade else 1, (2,), np.uint16, shared),
        _src("curv", cap if has_curv else 1, (), np.float32, shared),
    )
    # the walk sets them for the brick's rays only (``order``: those crossing it); ``start``
    # and ``walked`` (and ``count`` without a cache) are read for those only: reused
    start, walked = _ray_scratch(state, "start", nrays), _ray_scratch(state, "walked", nrays)
    count = np.zeros(nrays, np.int64) if build_cache else _ray_scratch(state, "count", nrays)
    geo = np.array([gx, gy, gz, off[2], off[1], off[0]], np.int64)
    per = max(_group() if report else nchunk, 1)  # groups of chunks: see progress
    if not nchunk:
        report(1.0)  # no ray crosses the brick
    for c0 in range(0, nchunk, per):
        c1 = min(c0 + per, nchunk)
        nb.walk_brick(
            vol, *maps, cv, seg["a"], seg["b"], seg["t"], j0, j1, t["step"], order,
            chunk_ptr[c0 : c1 + 1], c1 - c0, t["ids"], t["memb"], t["alpha_r"], t["alpha_w"],
            t["cols"], t["light"], t["tab"], shade, has_curv, build_cache, state.occlusion_free,
            chunk_base[c0:c1], _tables.ERT, geo, state.st, state.bits, state.vis, state.asg,
            *src, start, count, walked,
        )  # fmt: skip
        report(c1 / nchunk)
    state.stats["samples_walked"] += int(walked[order].sum())
    state.stats["bricks"] += 1
    if not build_cache:
        return None
    dest = np.zeros(nrays, np.int64)
    np.cumsum(count[:-1], out=dest[1:])
    e = int(dest[-1] + count[-1])
    take = _Arena.fresh if arena is None else arena.take
    out = (
        take("lut", e, (), np.uint16),
        take("j", e, (), np.int32),
        take("sh", e if shade else 0, (2,), np.uint16),
        take("curv", e if has_curv else 0, (), np.float32),
    )
    # the brick's rays, chunk by chunk (a ray's entries go to the same place in any order)
    nk.compact(order, chunk_ptr, nchunk, start, count, dest, *src, *out, shade, has_curv)
    del src
    fill_shade = shade and shade_all
    fill_curv = has_curv and (curvature_all or not shade)
    if fill_shade or fill_curv:  # behind early ray termination: not composited yet
        nb.fill_range(dest, count, out[0], out[1], out[2], out[3], seg["a"], seg["b"], seg["t"],
                      t["step"], j0, j1, vol, cv, geo, t["ids"], t["tab"], fill_shade, fill_curv,
                      np.uint32(16))  # fmt: skip
    codes = (vol >> np.uint32(16)).astype(np.uint16) if keep_codes and shade else None
    return BrickCache(brick, dest, count, *out, codes=codes, offset=off)


def _ray_scratch(state: RayState, name: str, n: int) -> np.ndarray:
    """Return a per-ray int64 buffer of ``state``, reused from brick to brick (no page faults)."""
    key = "scratch_" + name
    a = state.stats.get(key)
    if a is None or len(a) != n:
        a = state.stats[key] = np.zeros(n, np.int64)
    return a


class _Arena:
    """Reused memory for the bricks' cache entries of one analysis, until they are merged.

    Fresh memory costs page faults (as much as the copy into it); the entries of every brick
    are taken one after another from buffers kept for the next analysis, grown to what the
    last one needed.  One analysis at a time holds the arena (:data:`_ARENA_LOCK`); others
    take fresh arrays.
    """

    def __init__(self) -> None:
        self.used: dict = {}
        self.need: dict = {}

    @staticmethod
    def fresh(name, n, tail, dtype):
        """Return a fresh array of ``n`` rows."""
        return np.empty((n, *tail), dtype)

    def take(self, name, n, tail, dtype):
        """Return the next ``n`` rows of buffer ``name`` (fresh ones when it is full)."""
        if n == 0:
            return np.empty((0, *tail), dtype)
        used = self.used.get(name, 0)
        self.used[name] = used + n
        self.need[name] = used + n
        buf = _ARENA_BUFFERS.get(name)
        if buf is None or len(buf) < used + n:
            return np.empty((n, *tail), dtype)
        return buf[used : used + n]

    def release(self) -> None:
        """Grow the buffers that were short to what this analysis needed (for the next)."""
        for name, need in self.need.items():
            buf = _ARENA_BUFFERS.get(name)
            if buf is None or len(buf) < need:
                tail, dtype = _ARENA_KINDS[name]
                _ARENA_BUFFERS.pop(name, None)
                _ARENA_BUFFERS[name] = np.empty((int(need * 1.1) + 1, *tail), dtype)


_ARENA_KINDS = {"lut": ((), np.uint16), "j": ((), np.int32), "sh": ((2,), np.uint16),
                "curv": ((), np.float32)}  # fmt: skip
_ARENA_LOCK = threading.Lock()
_ARENA_BUFFERS: dict = {}


def _merge(caches, state) -> dict:
    """Return the bricks' entries per ray, in view order (= the whole walk's order)."""
    _, nb = _kernels()
    nrays = len(state.st)
    total = np.zeros(nrays, np.int64)
    for c in caches:
        total += c.count
    dest = np.zeros(nrays, np.int64)
    np.cumsum(total[:-1], out=dest[1:])
    e = int(dest[-1] + total[-1]) if nrays else 0
    shade = state.tables["shade"]
    has_curv = any(c.curvature.size for c in caches)
    m = {
        "lut": np.empty(e, np.uint16),
        "steps": np.empty(e, np.int32),
        "shading": np.empty((e if shade else 0, 2), np.uint16),
        "curvature": np.empty(e if has_curv else 0, np.float32),
    }
    shared = _shared_buffers(caches, shade, has_curv)
    if shared is not None:  # every brick's entries in one buffer each: one pass
        bufs, offsets = shared
        used = [(c, o) for c, o in zip(caches, offsets, strict=True) if o is not None]
        starts = np.empty((len(used), nrays), np.int64)
        counts = np.empty((len(used), nrays), np.int64)
        for q, (c, o) in enumerate(used):
            np.add(c.start, o, out=starts[q])
            counts[q] = c.count
        caches.clear()
        nb.place_all(dest, starts, counts, *bufs, m["lut"], m["steps"], m["shading"],
                     m["curvature"], shade, has_curv)  # fmt: skip
        return {"start": dest, "count": total, **m}
    fill = np.zeros(nrays, np.int64)
    while caches:
        c = caches.pop(0)  # dropped as soon as copied
        nb.place(dest, fill, c.start, c.count, c.lut, c.steps, c.shading, c.curvature, m["lut"],
                 m["steps"], m["shading"], m["curvature"], shade, has_curv)  # fmt: skip
    return {"start": dest, "count": total, **m}


def _base(a: np.ndarray) -> np.ndarray:
    while isinstance(a.base, np.ndarray):
        a = a.base
    return a


def _shared_buffers(caches, shade, has_curv):
    """Return the buffers of every brick's entries and each one's offset in them, or None.

    The bricks' entries come one after another from the arena's buffers (:class:`_Arena`):
    then one pass of :func:`_numba_bricks.place_all` merges them.  ``None`` when some brick's
    entries are elsewhere (fresh arrays) or not at the same row of every buffer; a brick
    without entries has offset ``None``.
    """
    names = ["lut", "steps"] + (["shading"] if shade else []) + (["curvature"] if has_curv else [])
    bases: dict = {}
    offsets = []
    for c in caches:
        if not len(c.lut):
            offsets.append(None)
            continue
        off = None
        for name in names:
            a = getattr(c, name)
            base = bases.setdefault(name, _base(a))
            if _base(a) is not base or not a.flags.c_contiguous or len(a) != len(c.lut):
                return None
            rows, rem = divmod(a.ctypes.data - base.ctypes.data, a.strides[0])
            if rem or (off is not None and rows != off):
                return None
            off = rows
        offsets.append(off)
    if not bases:
        return None
    none = {"shading": np.zeros((1, 2), np.uint16), "curvature": np.zeros(1, np.float32)}
    bufs = []
    for name in ("lut", "steps", "shading", "curvature"):
        b = bases.get(name)
        bufs.append(none[name] if b is None else b)
    return bufs, offsets


def finish(state: RayState, caches=None, *, refill=None, seconds=None, fill=None) -> RayAnalysis:
    """Return the analysis of the walked rays (every brick walked once, in view order).

    ``caches``: the bricks' :class:`BrickCache` in view order (consumed); merged into the
    result's :class:`RayCache`.  ``refill(cache, tab)``: recomputes shading after a change of
    light (:func:`analyze_bricked` passes one that re-reads the bricks).  ``fill(cache,
    alpha, tab)``: shades the entries compositing at opacities ``alpha`` can reach, for a
    cache whose bricks were walked with ``shade_all=False`` (:func:`_filler`).
    """
    spec, cam = state.spec, state.camera
    k = len(spec.structures)
    st = state.st
    rgba = np.empty((len(st), 4))
    np.minimum(st[:, :3], 1.0, out=rgba[:, :3])
    rgba[:, 3] = 1.0 - st[:, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        cimg = np.where(st[:, 6] > 0.0, st[:, 5] / np.where(st[:, 6] > 0, st[:, 6], 1.0), 0.0)
    aimp = 1.0 - st[:, 4]
    asg = state.asg[:k]
    nsamp = int(state.seg["n"].sum())
    secs = time.perf_counter() - state.stats["t_start"] if seconds is None else seconds
    stats = {
        "rays": len(st),
        "rays_hit": int(np.count_nonzero(state.seg["n"])),
        "samples": nsamp,
        "samples_walked": state.stats["samples_walked"],
        "samples_per_second": nsamp / secs if secs > 0 else 0.0,
        "seconds": secs,
        "backend": "numba",
        "sample_distance": state.tables["step"],
        "occlusion_free": state.occlusion_free,
        "assigned_cap": state.stats.get("assigned_cap"),
        "bricks": state.stats["bricks"],
    }
    t = state.tables
    stats["params"] = _params(state.opacities, t["cols"], t["mats"], spec.rendering.light_direction)
    if not state.occlusion_free:
        asg = np.full((k, len(st)), np.nan, np.float32)
        aimp = np.full(len(st), np.nan, np.float32)
    cache = None
    if caches is not None:
        m = _merge(caches, state)
        h, w = cam.height, cam.width
        dummy = np.zeros((2, 2, 2), np.uint32 if t["shade"] else np.uint16)
        lazy = {
            "steps": m["steps"],
            "a": state.seg["a"],
            "b": state.seg["b"],
            "t": state.seg["t"],
            "step": t["step"],
            "volume": dummy,  # every entry is filled: compositing never reads it
            "curvature_volume": walk_curvature(None, "numba"),
            "shading_key": _tables.shading_key(t["light"], k) if t["shade"] else b"",
            "refill": refill,
            "fill": fill,
            "filled": None,  # the opacities whose reach is shaded (None: only the walk's)
        }
        cache = RayCache(
            spec=spec.with_opacities(state.opacities), camera=cam, ids=t["ids"],
            membership=t["memb"], ratio=t["ratio"], start=m["start"], count=m["count"],
            lut=m["lut"], shading=m["shading"], curvature=m["curvature"],
            assigned=np.asarray(asg, np.float32).reshape(k, h, w),
            present=state.bits.reshape(h, w).copy(), backend="numba", stats=dict(stats),
            lazy=lazy, importance_accumulated=np.asarray(aimp, np.float32).reshape(h, w),
        )  # fmt: skip
        stats["cache_entries"] = len(m["lut"])
        stats["cache_bytes"] = cache.nbytes
    vis = np.ascontiguousarray(state.vis)
    return _finish(rgba, vis, asg, state.bits.copy(), cimg, spec, cam, stats, cache, aimp)


def _pieces(volume: Volume, bricks, curvature, skip=(), skip_curvature=(), scratch=None,
            wanted=None):  # fmt: skip
    """Each brick's piece of ``volume`` (a view), its offset and curvature piece.

    The piece is ``None`` for bricks in ``skip`` and the curvature piece for bricks in
    ``skip_curvature`` (both known from the memo).  ``curvature``: a whole-volume array or
    a :class:`~dvr_perception.rays.curvature_field.CurvatureField` (its piece computed here).
    ``scratch``: a dict in which a whole-volume array's pieces are copied into one reused
    buffer (valid until the next piece; fresh memory costs page faults), else fresh arrays.
    ``wanted(brick)`` False (asked when the brick's turn comes): neither piece is made and
    the offset is ``None``.
    """
    for br in bricks:
        ranges = br.voxels(volume.data.shape)
        (z0, z1), (y0, y1), (x0, x1) = ranges
        sl = (slice(z0, z1), slice(y0, y1), slice(x0, x1))
        piece = cv = None
        if wanted is not None and not wanted(br):
            yield br, None, None, None  # no offset: skipped
            continue
        if curvature is None or br in skip_curvature:
            pass
        elif isinstance(curvature, np.ndarray) and scratch is not None:
            shape = (z1 - z0, y1 - y0, x1 - x0)
            buf = scratch.get("curvature")
            if buf is None or buf.size < math.prod(shape):
                buf = scratch["curvature"] = np.empty(math.prod(shape), np.float32)
            cv = buf[: math.prod(shape)].reshape(shape)
            np.copyto(cv, curvature[sl], casting="unsafe")
        elif isinstance(curvature, np.ndarray):
            cv = np.ascontiguousarray(curvature[sl], np.float32)
        else:
            cv = curvature.piece(ranges)
        if br not in skip:
            labels = None if volume.labels is None else volume.labels[sl]
            piece = Volume(volume.data[sl], volume.spacing, volume.origin, labels=labels)
        yield br, piece, (z0, y0, x0), cv


#: Derived volumes of recent bricked analyses, per volume (while the memory limit allows).
_MEMO: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: The bricks' derived volumes (about 7 bytes a voxel) are kept between analyses of a volume
#: while they take at most this share of the room the bricked analysis leaves under the
#: memory limit (:func:`~dvr_perception.rays.memory.plan`'s estimate of its peak); their
#: curvature pieces (4 bytes a voxel; of a field, or of a whole-volume array while it lives)
#: too while both fit.  A volume bricked only because it
#: is a little too large for the whole-volume analysis then costs what the whole volume costs
#: from its second analysis on.  When not all of them fit, the front bricks of the analyses
#: without a cache are kept while they fit (:class:`_PartialMemo`): the rest are derived again
#: each time.
MEMO_SHARE = 0.5


def _memo_bytes(volume) -> int:
    try:
        return memory.array_bytes(_MEMO.get(volume))
    except TypeError:  # not weak-referenceable: nothing memoised
        return 0


def _memo_drop(volume) -> None:
    with contextlib.suppress(TypeError):  # not weak-referenceable: nothing memoised
        _MEMO.pop(volume, None)


def _buffers_bytes(_volume=None) -> int:
    """Bytes of the buffers every bricked analysis reuses (kept between analyses)."""
    return memory.array_bytes(dict(_SRC), dict(_ARENA_BUFFERS), dict(_CURV_SCRATCH))


def _buffers_drop(_volume=None) -> None:
    """Free the reused buffers (those in use by a running analysis live on until it ends)."""
    for d in (_SRC, _ARENA_BUFFERS, _CURV_SCRATCH):
        d.clear()


def _runs_bytes(_volume=None) -> int:
    with _RUNS_LOCK:
        return memory.array_bytes(list(_RUNS.values()))


def _runs_drop(_volume=None) -> None:
    with _RUNS_LOCK:
        _RUNS.clear()


#: :func:`~dvr_perception.rays.memory.plan` counts (and may drop) the memos and buffers.
memory.keeps("bricks", _memo_bytes, _memo_drop)
memory.keeps("bricks_buffers", _buffers_bytes, _buffers_drop, per_volume=False)
memory.keeps("bricks_runs", _runs_bytes, _runs_drop, per_volume=False)


def _curvature_key(curvature):
    """Return what identifies the curvature pieces a memo holds.

    A field of the same volume, sigma and structure ranges/labels gives the same pieces; a
    whole-volume array (or its pages) gives them while it lives (its identity; like the
    checked curvature, an array is assumed not to change in place).
    """
    if curvature is None:
        return None
    if isinstance(curvature, np.ndarray):
        return ("array", id(curvature), curvature.ctypes.data, curvature.shape)
    if not hasattr(curvature, "spec"):  # pages of a whole-volume array (CurvaturePages)
        return ("pages", id(curvature), curvature.shape)
    structures = tuple((s.range, s.label) for s in curvature.spec.structures)
    return (curvature.sigma, structures)


class _PartialMemo(dict):
    """The derived volumes of the bricks that fit ``budget`` bytes (all of them do not).

    Bricks are added as they are walked (front to back) until the budget is spent; the
    others are derived again by every analysis.  A render of a volume too large for the
    memo then re-derives only the bricks behind those kept.  When shading, the entries are
    compact (:func:`_derive_compact`: no voxel records, about 2 bytes a voxel instead of 7,
    so about 3.5 times as many bricks fit); their records are made again from the piece.
    """

    def __init__(self, budget: float) -> None:
        super().__init__()
        self.budget = float(budget)
        self.used = 0

    def offer(self, brick, derived) -> bool:
        """Keep ``derived`` for ``brick`` when it fits the budget; return whether it was kept."""
        size = memory.array_bytes(derived)
        if self.used + size > self.budget:
            return False
        self[brick] = derived
        self.used += size
        return True


def _memo(volume, state, bricks, room, curvature=None) -> tuple[dict | None, dict | None]:
    """Return the memos of ``volume``'s brick-derived volumes and curvature pieces, or None.

    ``room``: bytes the memos may take (:data:`MEMO_SHARE` of what the analysis leaves free).
    The derived volumes depend on the tables only, the curvature pieces on the field only:
    analyses with and without curvature share the derived volumes.
    """
    t = state.tables
    lut = t["lut"]
    key = (
        float(lut.lo), float(lut.scale), int(lut.size), t["ids"].tobytes(), t["memb"].tobytes(),
        t["labels"], t["shade"], tuple(br.cells for br in bricks),
    )  # fmt: skip
    held = sum(math.prod(b - a for a, b in br.voxels(volume.data.shape)) for br in bricks)
    partial = 7 * held > room
    least = _partial_voxel_bytes(t) if partial else 7  # a brick's entry, bytes a voxel
    if partial and room < least * max(math.prod(b - a for a, b in br.voxels(volume.data.shape))
                                      for br in bricks):  # fmt: skip
        _MEMO.pop(volume, None)  # not even one brick
        return None, None
    hit = _MEMO.get(volume)
    if hit is None or hit["key"] != key:
        hit = {
            "key": key,
            "bricks": {},
            "curvature_key": None,
            "curvature": {},
            "curvature_ref": None,
        }
        _MEMO[volume] = hit  # the newest tables only
    if partial != isinstance(hit["bricks"], _PartialMemo):  # (a memo of the other kind)
        hit["bricks"] = _PartialMemo(room) if partial else {}
    if partial:
        memo = hit["bricks"]
        memo.budget = room
        # less room than when they were kept: start again (dropping only the back bricks
        # measured a 6.1 GiB peak in the 1024 CT's bench, over its 5.9 GiB limit)
        if memo.used > room:
            memo.clear()
            memo.used = 0
        hit["curvature"], hit["curvature_key"] = {}, None
        return memo, None
    if curvature is None:
        return hit["bricks"], None
    if 11 * held > room:
        hit["curvature"], hit["curvature_key"] = {}, None
        return hit["bricks"], None
    ckey = (_curvature_key(curvature), tuple(br.cells for br in bricks))
    array = not hasattr(curvature, "spec")  # an array or its pages, not a field
    same = hit["curvature_key"] == ckey and (not array or hit["curvature_ref"]() is curvature)
    if not same:  # (an array of the same id and address is a new one once the old died)
        hit["curvature"], hit["curvature_key"] = {}, ckey
        hit["curvature_ref"] = weakref.ref(curvature) if array else None
    return hit["bricks"], hit["curvature"]


def _records_kept(memo, brick) -> bool:
    """Whether ``memo`` keeps ``brick``'s voxel records (not a compact entry, or none)."""
    return memo is not None and memo.get(brick, (None,))[0] is not None


#: A :class:`_PartialMemo` keeps compact entries when shading (:func:`_derive_compact`: the
#: records made again from the piece at each analysis; about 2 bytes a voxel instead of 7).
#: The 1024 x 1024 x 904 CT under the default limit kept 17 of its 64 bricks at 7 bytes.
#: ``False``: whole entries (the same results).
COMPACT_MEMO = True


def _partial_voxel_bytes(tables) -> int:
    """Bytes per voxel of a :class:`_PartialMemo` entry (:func:`_derive_compact`), rounded up."""
    if not tables["shade"] or not COMPACT_MEMO:
        return 7  # derive's volumes as they are (the table index is the walk's volume)
    return 2 if tables["lut"].size <= 256 else 3


def _refiller(volume_ref, bricks, kept, state):
    """Recompute every entry's shading brick by brick (after a change of light).

    ``kept``: per brick its normal codes (or voxel records), their shift and offset
    (:func:`walk`'s ``keep_codes``), ``None`` for a brick whose entries' normal codes are
    computed from the volume (:func:`_numba_bricks.fill_from_data`, at each change of
    light; :data:`REFILL_FROM_DATA`), or ``None`` for all of them.
    """
    kept = [None] * len(bricks) if kept is None else list(kept)

    def todo(missing, from_data):
        pieces = _pieces(volume_ref(), missing, None) if missing and not from_data else iter(())
        for br, k in zip(bricks, kept, strict=True):
            if k is not None:  # (codes or records, their shift, offset)
                yield (br, *k)
            elif not from_data:  # the next missing brick, derived one at a time
                _, piece, off, _ = next(pieces)
                yield br, _records(piece, state), 16, off

    def refill(cache, tab):
        _, nb = _kernels()
        seg, t = state.seg, state.tables
        gz, gy, gx = state.geometry.shape
        missing = [br for br, k in zip(bricks, kept, strict=True) if k is None]
        volume = volume_ref() if missing else None
        if missing and volume is None:
            raise DVRInputError(
                "cache: the volume of this bricked analysis is gone; a new light needs it"
            )
        # from the volume's data only when it is the rays' whole grid (it always is here)
        from_data = REFILL_FROM_DATA and (volume is None or volume.data.shape == (gz, gy, gx))
        for br, vol, shift, off in todo(missing, from_data):
            j0, j1 = _runs(state, br)
            geo = np.array([gx, gy, gz, off[2], off[1], off[0]], np.int64)
            nb.fill_range(cache.start, cache.count, cache.lut, cache.lazy["steps"], cache.shading,
                          cache.curvature, seg["a"], seg["b"], seg["t"], t["step"], j0, j1, vol,
                          np.zeros((2, 2, 2), np.float32), geo, cache.ids, tab, True, False,
                          np.uint32(shift))  # fmt: skip
        if missing and from_data:  # every entry still unset is in a brick not kept
            spacing = np.asarray(volume.spacing, float)
            aspect = (2.0 * spacing / spacing.mean()).astype(np.float32)  # as the records'
            nb.fill_from_data(cache.start, cache.count, cache.lut, cache.lazy["steps"],
                              cache.shading, seg["a"], seg["b"], seg["t"], t["step"],
                              volume.data, aspect, cache.ids, tab)  # fmt: skip

    return refill


#: After a change of light, the bricks whose normal codes were not kept shade their cache
#: entries from the volume itself (8 codes per entry, :func:`_numba_bricks.fill_from_data`)
#: instead of deriving their voxel records again (every voxel of every such brick).  The
#: 1024 x 1024 x 904 CT (61 of 64 bricks without codes, loaded 2-core machine): 29-45 s per
#: change of light for the optimiser's cache of 96^2 rays, 0.6 s from the volume; its 512^2
#: cache 58 s, 10 s.  ``False``: derive them (the same shading).
REFILL_FROM_DATA = True


#: Keep the bricks' normal codes for a change of light (front bricks first) while they take at
#: most this share of the memory limit (and of the room the memo rule leaves).
KEEP_CODES_SHARE = 0.25


def analyze_bricked(volume: Volume, spec: StructureSpec, camera: Camera, *, brick=(64, 64, 64),
                    opacities=None, curvature=None, build_cache: bool = True,
                    occlusion_free: bool = True, memory_limit=None, progress=None,
                    segments=None, exact: bool = False) -> RayAnalysis:  # fmt: skip
    """:func:`~dvr_perception.rays.engine.analyze`, walking the volume brick by brick.

    Parameters
    ----------
    brick : tuple of int
        Cells per brick ``(z, y, x)``.
    volume, spec, camera, opacities, curvature, build_cache, occlusion_free, memory_limit, exact
        As :func:`~dvr_perception.rays.engine.analyze` (``curvature``: a whole-volume array,
        a :class:`~dvr_perception.rays.curvature_field.CurvatureField`, or ``None``).
    progress : callable, optional
        Called from the calling thread with the fraction done (float in [0, 1]): 0.0 first,
        after each brick walked (its curvature piece included), 1.0 once the bricks' caches
        are merged; at most about 100 calls, non-decreasing.  A callback that raises
        :class:`StopIteration` cancels the analysis with
        :class:`~dvr_perception.errors.DVRCancelled`.
    segments : dict, optional
        The camera's rays when the caller has made them (:meth:`RayState.start`).

    Examples
    --------
    >>> from dvr_perception.rays.engine import analyze
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> cam = Camera.from_view(vol.bounds, width=16, height=16)
    >>> whole = analyze(vol, spec, cam)
    >>> parts = analyze_bricked(vol, spec, cam, brick=(5, 7, 9))
    >>> bool(np.array_equal(whole.rgba, parts.rgba))
    True
    """
    return analyze_bricked_views(
        volume, spec, [camera], brick=brick, opacities=opacities, curvature=curvature,
        build_cache=build_cache, occlusion_free=occlusion_free, memory_limit=memory_limit,
        progress=progress, segments=None if segments is None else [segments], exact=exact,
    )[0]  # fmt: skip


def analyze_bricked_views(volume: Volume, spec: StructureSpec, cameras, *, brick=(64, 64, 64),
                          opacities=None, curvature=None, build_cache: bool = True,
                          occlusion_free: bool = True, memory_limit=None, progress=None,
                          segments=None, exact: bool = False) -> list[RayAnalysis]:  # fmt: skip
    """:func:`analyze_bricked` for several cameras, deriving each brick once for all of them.

    Cameras that meet the bricks in the same order (e.g. one view at several resolutions, as
    the optimiser uses) share one pass over the volume: each brick's derived volumes and
    curvature are computed once and every camera's rays walk it.  The results equal one
    :func:`analyze_bricked` per camera.  ``progress`` and ``exact``: as
    :func:`analyze_bricked`, over all the cameras; ``segments``: per camera its rays, when
    already made.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> big = Camera.from_view(vol.bounds, width=16, height=16)
    >>> small = Camera.from_view(vol.bounds, width=8, height=8)
    >>> both = analyze_bricked_views(vol, spec, [big, small], brick=(5, 7, 9))
    >>> one = analyze_bricked(vol, spec, small, brick=(5, 7, 9))
    >>> bool(np.array_equal(both[1].rgba, one.rgba))
    True
    """
    t0 = time.perf_counter()
    cameras = list(cameras)
    for cam in cameras:
        _check_inputs(volume, spec, cam, "numba")
    report = reporter(progress)
    curv = _check_curvature(curvature, volume)
    every = split(volume.data.shape, brick)
    rng = _grid.scalar_range(volume)
    states = [
        RayState.start(
            Geometry.of(volume),
            spec,
            cam,
            scalar_range=rng,
            opacities=opacities,
            occlusion_free=occlusion_free,
            segments=None if segments is None else segments[n],
            exact=exact,
        )
        for n, cam in enumerate(cameras)
    ]
    groups: dict = {}  # one pass over the volume per order of the bricks
    for n, st in enumerate(states):
        groups.setdefault(tuple(view_order(every, st)), []).append(n)
    cap = memory.limit(memory_limit)
    room = _room(volume, states, brick, curv, build_cache, cap)
    report(0.0)
    arena = _Arena() if build_cache and _ARENA_LOCK.acquire(blocking=False) else None
    try:
        results = _views(volume, states, every, groups, curv, cap, build_cache, report, room,
                         arena, t0)  # fmt: skip
    finally:
        if arena is not None:
            arena.release()
            _ARENA_LOCK.release()
    report(1.0)
    return results


def _views(volume, states, every, groups, curv, cap, build_cache, report, room, arena, t0):
    """Walk the passes of :func:`analyze_bricked_views`; return the finished analyses."""
    out = [None] * len(states)
    ncam = len(states)
    walked = 0  # cameras whose pass is done: each pass's share of the bar is its cameras'
    for order, members in groups.items():
        bricks = [every[i] for i in order]
        share = report.sub(0.95 * walked / ncam, 0.95 * (walked + len(members)) / ncam)
        got = _pass(volume, [states[n] for n in members], bricks, curv, cap, build_cache, share,
                    room, arena)  # fmt: skip
        walked += len(members)
        for n, res in zip(members, got, strict=True):
            out[n] = res
    seconds = time.perf_counter() - t0
    results = [
        finish(st, caches, refill=refill, fill=fill, seconds=seconds)
        for st, (caches, refill, fill) in zip(states, out, strict=True)
    ]
    return results


#: Below this many bricks a brick's walk also reports inside (groups of chunks).  Small bricks
#: cover few of the image's tiles, so a group of chunks shares its work unevenly between the
#: threads (measured 1.5x slower for 32 bricks of 64^3 on cthead at 512^2); many bricks report
#: often enough one by one.
INNER_PROGRESS_BRICKS = 16


def _room(volume, states, brick, curv, build_cache, cap) -> float:
    """Bytes the memos (or the kept normal codes) may take: :data:`MEMO_SHARE` of the room.

    The room is what the limit leaves beside the bricked analyses of ``states`` (each one's
    :func:`~dvr_perception.rays.memory.plan` estimate, the memos aside; what every analysis
    of the volume holds, the volume itself first, counted once).
    """
    peaks = [_peak(volume, st, brick, curv, build_cache, cap) for st in states]
    held = max(h for _, h in peaks)
    return MEMO_SHARE * max(cap - held - sum(p - h for p, h in peaks), 0)


def _peak(volume, state, brick, curv, build_cache, cap) -> tuple[float, float]:
    """Bytes the bricked analysis of ``state``'s camera holds at its peak (the memos aside).

    And of those what every analysis of the volume holds (``plan``'s ``held``).
    """
    t = state.tables
    try:
        p = memory.plan(
            volume, len(state.st), int(state.seg["n"].sum()), k=len(state.spec.structures),
            shade=t["shade"], curvature=curv is not None, build_cache=build_cache, lut=t["lut"],
            membership=t["memb"], memory_limit=max(int(cap), 2**20), brick=brick,
            curvature_array=isinstance(curv, np.ndarray) or hasattr(curv, "kernel_arg"),
        )  # fmt: skip
    except DVRInputError:  # more than the limit even in bricks: no room for memos
        return float(cap), 0.0
    return p["bricked"] - p["memo"], p["held"]


def _alive(states, brick) -> bool:
    """Whether a ray of ``states`` that meets ``brick`` is still short of early termination."""
    for st in states:
        if st.occlusion_free:
            return True  # every sample counts (assigned opacities)
        j0, j1 = _runs(st, brick)
        if _kernels()[1].any_alive(j0, j1, st.st, _tables.ERT):
            return True
    return False


def _pass(volume, states, bricks, curv, cap, build_cache, report=None, room=0.0,
          arena=None) -> list:  # fmt: skip
    """Walk ``bricks`` (in the states' common view order) for every state; caches and refill.

    Each brick is read and derived once (or taken from the memo) for all the states;
    ``report(fraction)`` follows after each brick.  Rendering only (no occlusion-free
    shares), a brick behind every ray's early termination is neither read nor walked.
    ``room``: bytes the memos may take; ``arena``: where the bricks' entries go.
    """
    memo, cmemo = _memo(volume, states[0], bricks, room, curv)
    # the codes stay with the cache (counted as the memo would be: within the room), brick by
    # brick in view order while they fit (a change of light re-derives the others)
    # (a partial memo's bricks keep their records; codes for the others, as without a memo)
    codes_kept = memo is None or isinstance(memo, _PartialMemo)
    keep = min(KEEP_CODES_SHARE * cap, room) if build_cache and codes_kept else 0.0
    # (compact entries of a partial memo: their pieces are read, for the voxel records)
    known = {br for br, d in memo.items() if d[0] is not None} if memo is not None else set()
    locked = _CURV_SCRATCH_LOCK.acquire(blocking=False)
    try:
        return _pass_locked(volume, states, bricks, curv, build_cache, report, memo, cmemo, keep,
                            known, locked, arena)  # fmt: skip
    finally:
        if locked:
            _CURV_SCRATCH_LOCK.release()


#: The reused buffer of whole-volume curvature pieces (:func:`_pieces`) and its lock.
_CURV_SCRATCH: dict = {}
_CURV_SCRATCH_LOCK = threading.Lock()


def _pass_locked(volume, states, bricks, curv, build_cache, report, memo, cmemo, keep, known,
                 locked, arena=None) -> list:  # fmt: skip
    """:func:`_pass` once its memos are known (``locked``: the curvature scratch is ours)."""
    caches = [[] if build_cache else None for _ in states]
    kept = [[] for _ in states]
    # with every brick's normal codes kept (memo or codes), entries behind early ray
    # termination are shaded only when a re-evaluation can reach them (_filler)
    shape = volume.data.shape
    sizes = [2 * math.prod(b - a for a, b in br.voxels(shape)) for br in bricks]  # their codes
    keep_all = bool(keep) and sum(sizes) <= keep
    partial = isinstance(memo, _PartialMemo)  # some bricks only: re-derived after a new light
    full = memo is not None and not partial
    compact = partial and states[0].tables["shade"] and COMPACT_MEMO  # entries without records
    per = _partial_voxel_bytes(states[0].tables) if partial else 7
    # without a cache, one camera: codes only where the walk can shade (_derive_reached)
    reached = (REACHED_CODES and not build_cache and len(states) == 1
               and states[0].tables["shade"])  # fmt: skip
    lazy = build_cache and states[0].tables["shade"] and (full or keep_all)
    used = 0  # bytes of the codes kept
    # and their curvature too while the memo keeps the bricks' curvature pieces
    lazy_curv = lazy and curv is not None and cmemo is not None
    pieces_kept = []
    # rendering only: a brick behind every ray's termination is not read (nor its piece made)
    wanted = None if any(st.occlusion_free for st in states) else (lambda br: _alive(states, br))
    scratch = _CURV_SCRATCH if locked and cmemo is None else None  # memo pieces: their own
    pieces = _pieces(volume, bricks, curv, skip=known, skip_curvature=set(cmemo or ()),
                     scratch=scratch, wanted=wanted)  # fmt: skip
    for done, (br, piece, off, cv) in enumerate(pieces, 1):
        if off is None:  # not wanted
            if report:
                report(done / len(bricks))
            continue
        if cmemo is not None:
            cv = cmemo.setdefault(br, cv)
        pieces_kept.append(cv if lazy_curv else None)
        derived = memo.get(br) if memo is not None else None
        if derived is not None and derived[0] is None:  # a compact entry: its records anew
            derived = _expand(piece, states[0], derived, br, off, reached)
        if full and derived is None:
            derived = memo[br] = derive(piece, states[0])
        elif derived is None and reached:  # kept while the memo has room, else codes reached
            if partial and memo.used + per * piece.data.size <= memo.budget:
                if compact:
                    parts = _derive_compact(piece, states[0])
                    memo.offer(br, parts)
                    derived = _expand(piece, states[0], parts, br, off, True)
                else:
                    derived = derive(piece, states[0])
                    memo.offer(br, derived)
            else:
                derived = _derive_reached(piece, states[0], br, off)
        elif partial and derived is None:
            derived = derive(piece, states[0])  # (a cache keeps codes in the memo's room)
        if derived is None and len(states) > 1:
            derived = derive(piece, states[0])  # once for every state
        codes = None
        in_memo = partial and _records_kept(memo, br)  # its records serve a new light
        keep_br = bool(keep) and not in_memo and used + sizes[done - 1] <= keep
        used += sizes[done - 1] if keep_br else 0
        for n, st in enumerate(states):
            part = None  # this state's share of the brick's part of the bar
            if report and len(bricks) < INNER_PROGRESS_BRICKS:
                part = report.sub((done - 1 + n / len(states)) / len(bricks),
                                  (done - 1 + (n + 1) / len(states)) / len(bricks))  # fmt: skip
            c = walk(st, piece, br, offset=off, curvature=cv, build_cache=build_cache,
                     keep_codes=keep_br and codes is None, derived=derived,
                     progress=part, shade_all=not lazy,
                     curvature_all=not lazy_curv, arena=arena)  # fmt: skip
            if not build_cache or c is None:
                continue
            caches[n].append(c)
            if keep_br:
                codes = c.codes if codes is None else codes
                c.codes = None
                k = (codes, 0)
            else:
                k = (derived[0], 16) if _records_kept(memo, br) else None
            kept[n].append(None if k is None else (*k, off))
        if report:
            report(done / len(bricks))
    out = []
    for st, cs, kp in zip(states, caches, kept, strict=True):
        refill = fill = None
        if build_cache and st.tables["shade"]:
            kp = None if all(k is None for k in kp) else kp
            refill = _refiller(weakref.ref(volume), bricks, kp, st)
            if lazy:
                fill = _filler(bricks, kp, st, pieces_kept if lazy_curv else None)
        out.append((cs, refill, fill))
    return out


def _filler(bricks, kept, state, curvature=None):
    """Shade the entries of a lazily shaded bricked cache that compositing can reach.

    ``kept``: per brick its normal codes (or voxel records), their shift and offset;
    ``curvature``: per brick its curvature piece when the entries' curvature is lazy too
    (else every entry's curvature is set).  A call
    ``fill(cache, alpha, tab)`` before compositing at opacities ``alpha`` (per table entry)
    shades, brick by brick, every unset entry up to :func:`_numba_bricks.reach` at the
    entry-wise minimum of ``alpha`` and the opacities already served (lower opacities reach
    at least as far), with the shading table ``tab``; when ``alpha`` is nowhere below those,
    nothing is left to shade and it returns at once.  ``cache.lazy["filled"]`` is ``None``
    after a change of light (nothing shaded).
    """
    t, seg = state.tables, state.seg
    gz, gy, gx = state.geometry.shape

    def fill(cache, alpha, tab):
        z = cache.lazy
        done = z["filled"]
        if done is not None and np.all(alpha >= done):
            return
        lo = np.asarray(alpha, np.float64) if done is None else np.minimum(alpha, done)
        _, nb = _kernels()
        upto = np.empty(len(cache.start), np.int64)
        nb.reach(cache.start, cache.count, cache.lut, lo, _tables.ERT, upto)
        none = np.zeros((2, 2, 2), np.float32)
        pieces = [None] * len(bricks) if curvature is None else curvature
        for br, (vol, shift, off), cv in zip(bricks, kept, pieces, strict=True):
            j0, j1 = _runs(state, br)
            geo = np.array([gx, gy, gz, off[2], off[1], off[0]], np.int64)
            nb.fill_range(cache.start, upto, cache.lut, z["steps"], cache.shading,
                          cache.curvature, seg["a"], seg["b"], seg["t"], t["step"], j0, j1, vol,
                          none if cv is None else cv, geo, cache.ids, tab, True, cv is not None,
                          np.uint32(shift))  # fmt: skip
        z["filled"] = lo

    return fill
