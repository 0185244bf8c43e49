"""The ray-analysis engine: a DVR that also measures what every ray sees of every structure.

:func:`analyze` casts one ray per pixel through a :class:`~dvr_perception.volume.volume.Volume`
and returns a :class:`RayAnalysis`: the image plus, per structure and pixel, its visible
(occlusion-weighted) and assigned (importance-based, unoccluded) opacity, a presence bitmask
and the visibility-weighted boundary curvature.  With ``build_cache=True`` it keeps, per ray,
the compact list of samples with non-zero membership (:class:`RayCache`) so that
:func:`reevaluate` can apply new opacities, colours, materials or light direction without
touching the volume again.  :func:`analyze` checks its inputs, plans the memory
(:func:`~dvr_perception.rays.memory.plan`) and hands over to the whole-volume walk here or to
the bricked one (:mod:`~dvr_perception.rays.bricks`, imported when needed); what both walks
share lives below them in :mod:`~dvr_perception.rays._walk_setup`.

Conventions matched to ``vtkFixedPointVolumeRayCastMapper`` (``docs/vtk_conventions.md``):

* Tables: :func:`~dvr_perception.structures.transfer.build_lut` (VTK's table size/shift/scale
  over the data range); opacity ``1 - (1 - o m) ** (step / unit)`` for entries above 1e-4;
  opacities and colours rounded to 1/32767.
* Samples: box of voxel centres inset by 0.01 voxel and shrunk by 0.1 %, step of
  ``sample_distance`` world units, **phase anchored at the near clipping plane** that
  ``ResetCameraClippingRange`` would choose (first sample strictly past the entry).
* Classification: each cell corner's table index ``floor((v - lo) * scale)`` is interpolated
  trilinearly, then rounded up as VTK's fixed point does (``int(f * 32765/32768 + 32767/32768)``).
* Compositing front to back with premultiplied colour; early ray termination when the
  transmittance falls below 255/32767; final colour clamped to 1.
* Shading as VTK: central-difference normals (negative gradient, border voxel as its own
  neighbour) quantised with VTK's spherical direction encoding (65536 codes, one uint32 per voxel
  with the table index); per structure a shading table over the codes for the current light,
  two-sided (a normal facing away from the viewer is flipped): ``max(n.L, 0)`` and ``(n.H) ** p``
  (only where ``n.L > 0`` and ``n.H > 0.001``); both are trilinearly interpolated from the 8 cell
  corners' codes, and ``colour = c (ka I + kd I diffuse) + ks I specular`` (white specular),
  directional light ``L = x right + y up - z forward``, ``H = normalise(L - forward)``.
  The cache keeps the interpolated pair per entry (uint16, ``round(x * 65534)``), so new
  opacities, colours or ka/kd/ks re-composite only; a new light direction or specular power
  recomputes it.
"""

from __future__ import annotations

import functools
import threading
import time
import warnings
import weakref

import numpy as np

from dvr_perception._deprecation import renamed_keyword
from dvr_perception._numba import serial_below
from dvr_perception._progress import reporter
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.rays import _grid, _tables, memory
from dvr_perception.rays import _numpy_kernels as _npk
from dvr_perception.rays._results import RayAnalysis, RayCache
from dvr_perception.rays._walk_setup import (  # noqa: F401 - also engine's names for callers
    _CHUNKS,
    BACKENDS,
    TILE,
    _analysis,
    _check_curvature,
    _check_inputs,
    _finish,
    _group,
    _interleaved,
    _numba_kernels,
    _params,
    _plateau_entries,
    _segments,
    _segments_at,
    _tail_tables,
    _threads,
    _with_labels,
    ray_order,
    walk_curvature,
)
from dvr_perception.rays.camera import Camera
from dvr_perception.structures.spec import StructureSpec
from dvr_perception.structures.transfer import build_lut
from dvr_perception.volume.volume import Volume

__all__ = [
    "RayAnalysis",
    "RayCache",
    "analyze",
    "analyze_views",
    "reevaluate",
    "reevaluate_rgba",
    "rewalk",
    "rewalk_rgba",
]


def _pick_backend(backend: str):
    """Return the numba kernel module for ``backend`` (None: numpy); check ``"cuda"``'s needs.

    The CUDA back end walks the rays on the GPU; the rays and the per-volume arrays are made
    by the numba kernels (the same numbers as the CPU engine), so it needs them too.
    """
    if backend == "cuda":
        from dvr_perception.rays import _cuda

        _cuda.kernels()  # one clear error without numba.cuda or a device
    nk = _numba_kernels() if backend in ("auto", "numba", "cuda") else None
    if backend == "numba" and nk is None:
        raise DVRInputError(
            "backend: 'numba' was requested but numba cannot be imported "
            "(or DVR_PERCEPTION_NO_NUMBA is set); use backend='numpy' or 'auto'"
        )
    return nk


def _kind(backend: str, nk) -> str:
    """Return the back end that runs: ``"cuda"``, ``"numba"`` or ``"numpy"`` (``auto`` resolved).

    ``auto`` takes the GPU when numba finds a CUDA device (never the simulator), else numba,
    else numpy.
    """
    if backend == "cuda":
        return "cuda"
    if nk is None:
        return "numpy"
    if backend == "auto":
        from dvr_perception.rays import _cuda

        if _cuda.auto_usable():
            return "cuda"
    return "numba"


def analyze(
    volume: Volume,
    spec: StructureSpec,
    camera: Camera,
    *,
    opacities=None,
    curvature=None,
    backend: str = "auto",
    build_cache: bool = False,
    occlusion_free: bool = True,
    brick=None,
    memory_limit=None,
    progress=None,
    exact: bool = False,
    rays=None,
) -> RayAnalysis:
    """Render ``volume`` with ``spec`` from ``camera`` and measure every structure per pixel.

    Parameters
    ----------
    volume : Volume
        Scalar volume (any integer or float dtype).
    spec : StructureSpec
        1 to 32 structures: intensity ranges, or label ids looked up in ``volume.labels`` at
        each sample's nearest voxel (a label structure's voxels belong to it whatever their
        intensity; other voxels are classified by intensity).
    camera : Camera
        View and image size.
    opacities : array_like of float, optional
        ``K`` rendering opacities in [0, 1]; default each structure's ``render_opacity``.
    curvature : numpy.ndarray, CurvaturePages or CurvatureField, optional
        ``|mean curvature|`` per voxel ``[z, y, x]`` (0 off boundaries), e.g. from
        :func:`dvr_perception.rays.curvature_field.curvature_source` (pages, or a field
        computed brick by brick) or :func:`dvr_perception.rays.curvature.curvature_volume`
        (dense); looked up at the nearest voxel.
    backend : {"auto", "numba", "numpy", "cuda"}
        Kernel implementation; "auto" uses the GPU when numba finds a CUDA device (not with
        ``DVR_PERCEPTION_NO_CUDA=1``), else numba unless it is missing or
        ``DVR_PERCEPTION_NO_NUMBA=1``, else numpy.  "cuda" walks the rays on the GPU
        (:mod:`~dvr_perception.rays._cuda_kernels`, the ``gpu`` extra; the same results as
        "numba"); it analyses the whole volume at once whenever it fits ``memory_limit``
        (no ``brick``; a volume that fits only in bricks raises
        :class:`~dvr_perception.errors.DVRInputError`, where ``"auto"`` takes the bricked
        CPU analysis) and its cache re-evaluates on the CPU.
    build_cache : bool
        Keep the per-ray sample lists for :func:`reevaluate` (an optimiser's or a slider's
        repeated re-composites).  Off by default: the cache's walk must visit every sample
        behind early ray termination (a new opacity may move it), which costs 2-3x the
        analysis on deep volumes and memory; every measure is the same without it (the view
        without an enclosing layer is then walked again, :func:`rewalk`, DECISIONS D7).
    occlusion_free : bool
        Compute the occlusion-free ``assigned`` opacities, which need every sample of every ray
        (default).  ``False`` renders only: every ray stops at early ray termination as VTK's
        renderer does (about half the time on dense volumes); ``assigned`` is then NaN and
        ``present`` lists only the structures met before termination.  Needs
        ``build_cache=False``.
    brick : tuple of int, optional
        Analyse in bricks of this many cells ``(z, y, x)`` (:mod:`~dvr_perception.rays.
        bricks`; the same result).  By default the whole volume is analysed at once when it
        fits the memory limit (however many voxels), else in bricks sized by the limit
        (:func:`~dvr_perception.rays.memory.plan`).
    memory_limit : int or str, optional
        Bytes (or ``"8G"``) the analysis may use; default
        :func:`dvr_perception.rays.memory.limit`.  An analysis that cannot fit raises
        :class:`~dvr_perception.errors.DVRInputError` before allocating.
    progress : callable, optional
        Called from the calling thread with the fraction done, a float in [0, 1]: 0.0 first,
        then after each brick (bricked analysis) or each group of ray tiles (whole volume,
        numba), at most about 100 calls in all, non-decreasing, 1.0 last.  Never called
        inside a kernel; the result does not depend on it.  A callback that raises
        :class:`StopIteration` cancels the analysis:
        :class:`~dvr_perception.errors.DVRCancelled` is raised (nothing is returned).
    exact : bool
        Walk every sample behind early ray termination.  By default an analysis without the
        cache (``build_cache=False``, ``occlusion_free=True``) skips what cannot change a
        result there (DECISIONS D8): a structure whose ``assigned`` opacity on a ray has
        reached :data:`~dvr_perception.rays._grid.SATURATION` (1.0, where its presence has
        saturated) is not added to any more, and, once the ray's transmittance at the
        importances is below early ray termination, blocks of cells that can reach only
        such structures (or none) are jumped.  Every buffer is the exact walk's except
        ``assigned``, which is ``min(assigned, 1.0)`` (``stats["assigned_cap"]``); every
        measure's terms agree within 1e-6, but the thickness composition and
        ``assigned_share`` read ``assigned`` beyond saturation: pass ``exact=True`` (or
        build the cache, whose walk is always exact) for them.
    rays : array_like of int, optional
        Flat (row-major) pixel indices: walk only these rays; the other pixels see no volume
        (background, zeros in every buffer).  Each walked ray equals the whole image's to
        the last bit.  A partial view for what reads only some pixels, e.g. the view without
        an enclosing layer that :func:`recomposite` makes by walking again where an analysis
        has no cache (DECISIONS D7).  On the CPU (a ``"cuda"`` request walks them with
        numba).

    Returns
    -------
    RayAnalysis

    Examples
    --------
    >>> import numpy as np
    >>> from dvr_perception.structures.spec import RenderSettings, Structure
    >>> vol = Volume(np.full((8, 8, 8), 100, np.uint8))
    >>> spec = StructureSpec((Structure("slab", 0.5, (1, 1, 1), range=(50, 150)),),
    ...                      rendering=RenderSettings(shade=False))
    >>> cam = Camera.from_view(vol.bounds, width=8, height=8)
    >>> res = analyze(vol, spec, cam, backend="numpy")
    >>> bool(res.accumulated[4, 4] > 0.9), float(res.visible_share[0, 4, 4])
    (True, 1.0)
    """
    t_start = time.perf_counter()
    _check_inputs(volume, spec, camera, backend)
    report = reporter(progress)
    if not occlusion_free and build_cache:
        raise DVRInputError(
            "occlusion_free=False renders only (rays stop at early termination): "
            "pass build_cache=False with it"
        )
    k = len(spec.structures)
    imp = np.array([s.importance for s in spec.structures], float)
    imp = _tables.check_opacities(imp, k, "importance")
    ops = _tables.check_opacities(
        [s.render_opacity for s in spec.structures] if opacities is None else opacities, k
    )
    curv = _check_curvature(curvature, volume)
    if rays is not None and _kind(backend, _pick_backend(backend)) == "cuda":
        backend = "numba"  # a few rays: the CPU's walk (the GPU's rays are made whole)
    # a few rays of the image, image only: set up and walked alone (numba), then put in
    # place in the image; otherwise every ray is set up and those not asked for see nothing
    subset = None
    if rays is not None:
        rays = _checked_rays(rays, camera)
        if not build_cache and not occlusion_free and brick is None:
            subset = rays if _pick_backend(backend) is not None else None
    scene = _scene(volume, spec, camera, backend, subset)
    if rays is not None and subset is None:
        scene = (*scene[:-1], _only_rays(scene[-1], rays, camera))
    nk, _, _, lut, _, _, memb, seg = scene
    if not seg["n"].any():
        warnings.warn(
            f"camera sees none of volume {volume.name!r}; returning an empty image",
            DVRWarning,
            stacklevel=2,
        )
    kind = _kind(backend, nk)
    host_rays = kind != "cuda"  # seg: the CPU's rays (the GPU's are made by _cuda.rays_for)
    if kind == "cuda" and brick is not None:
        if backend == "cuda":
            raise DVRInputError(
                "brick: the cuda back end analyses the whole volume at once; bricked analysis "
                "is CPU only (backend='numba' or 'auto')"
            )
        kind = "numba"
    need = _plan(volume, spec, camera, seg, lut, memb, curv, build_cache, memory_limit, brick)
    skip = occlusion_free and not build_cache and not exact
    if kind == "cuda" and need["mode"] == "bricks":
        if backend == "cuda":
            raise DVRInputError(
                f"memory_limit: volume {volume.name!r} needs a bricked analysis within the "
                "memory limit, which the cuda back end does not do; use backend='auto' or "
                "'numba', or raise memory_limit"
            )
        kind = "numba"
    if need["mode"] == "whole" and curv is not None and not hasattr(curv, "kernel_arg"):
        from dvr_perception.rays.curvature_field import CurvatureField, CurvaturePages

        if isinstance(curv, CurvatureField):  # a field, read whole (paged as computed)
            whole = CurvaturePages.from_volume(
                curv.volume, curv.spec, sigma=curv.sigma, gradient_max=curv.globals
            )
            curv = _check_curvature(whole, volume)
    report(0.0)
    if need["mode"] == "bricks" and subset is not None:  # the bricked walk sets up every ray
        seg = _only_rays(_segments(nk, camera, volume, scene[1]), subset, camera)
        subset = None
    if need["mode"] == "bricks":  # the bricked walk (imported only when needed)
        from dvr_perception.rays.bricks import analyze_bricked

        res = analyze_bricked(
            volume, spec, camera, brick=need["brick"], opacities=ops, curvature=curv,
            build_cache=build_cache, occlusion_free=occlusion_free, memory_limit=memory_limit,
            progress=report, segments=seg if host_rays else None, exact=exact,
        )  # fmt: skip
        return _remember_source(res, volume, spec, backend, memory_limit)
    res = _analyze_whole(volume, spec, camera, scene, kind, imp, ops, curv, build_cache,
                         occlusion_free, report, t_start, skip, subset)  # fmt: skip
    return _remember_source(res, volume, spec, backend, memory_limit)


class _RayRow:
    """The shape a subset of ``m`` rays is walked in: one row of ``m`` pixels."""

    def __init__(self, m: int):
        self.height, self.width = 1, m


def _finish_rays(subset, rgba, vis, asg, present, cimg, spec, camera, stats, aimp):
    """:func:`_finish` of a walk of ``subset`` alone, put in place in the whole image.

    The rays not walked hold zeros and the background, as a ray that sees no volume.
    """
    n, k, m = camera.height * camera.width, len(spec.structures), len(subset)
    f32 = np.float32
    bg = np.asarray(spec.background, f32)
    part = (np.empty((m, 4), f32), np.empty((m, 3), f32), np.empty(m, f32),
            np.empty((k, m), f32), np.empty(m, f32))  # fmt: skip
    _numba_kernels().finish(
        np.ascontiguousarray(rgba[:m]), np.ascontiguousarray(vis[:, :m]),
        np.ascontiguousarray(cimg[:m]), bg, *part,
    )  # fmt: skip
    rgba32, image, acc = np.zeros((n, 4), f32), np.empty((n, 3), f32), np.zeros(n, f32)
    vis32, cimg32, bits = np.zeros((k, n), f32), np.zeros(n, f32), np.zeros(n, np.uint32)
    image[:] = np.clip(bg, 0.0, 1.0)
    rgba32[subset], image[subset], acc[subset] = part[0], part[1], part[2]
    vis32[:, subset], cimg32[subset], bits[subset] = part[3], part[4], present[:m]
    return _analysis(rgba32, image, acc, vis32, asg, bits, cimg32, spec, camera, stats, None,
                     aimp)  # fmt: skip


def _checked_rays(rays, camera: Camera) -> np.ndarray:
    """``rays`` as sorted, unique int64 flat pixel indices of ``camera``'s image (checked)."""
    n_rays = camera.width * camera.height
    try:
        sel = np.asarray(rays).ravel()
        ok = sel.dtype.kind in "iu" and (sel.size == 0 or (sel.min() >= 0 and sel.max() < n_rays))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DVRInputError(f"rays: expected flat pixel indices in [0, {n_rays}), got {rays!r}")
    sel = sel.astype(np.int64)
    if sel.size > 1 and not np.all(sel[1:] > sel[:-1]):  # flatnonzero's already are
        sel = np.unique(sel)
    return sel


def _only_rays(seg: dict, rays: np.ndarray, camera: Camera) -> dict:
    """``seg`` with no samples on every ray but ``rays`` (:func:`_checked_rays`)."""
    n_rays = camera.width * camera.height
    keep = np.zeros(n_rays, bool)
    keep[rays] = True
    out = dict(seg)
    out["n"] = np.where(keep, seg["n"], 0).astype(seg["n"].dtype)
    return out


#: Per analysis without a cache: what :func:`recomposite` walks again (the volume, spec,
#: back end and memory limit of the call).  Weak keys: dropped with the analysis.
_SOURCES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _remember_source(res: RayAnalysis, volume, spec, backend, memory_limit) -> RayAnalysis:
    if res.cache is None:
        _SOURCES[res] = (volume, spec, backend, memory_limit)
    return res


def _analyze_whole(volume, spec, camera, scene, kind, imp, ops, curv, build_cache,
                   occlusion_free, report, t_start, skip=False,
                   subset=None) -> RayAnalysis:  # fmt: skip
    """Analyse the whole volume at once (:func:`analyze` chose it): walk, cache and result.

    ``scene``: :func:`_scene`'s tuple; ``kind``: the back end that runs (:func:`_kind`);
    ``imp`` and ``ops``: the checked importances and opacities; ``curv``: the checked
    curvature array or None; ``skip``: the skipping walk behind early ray termination
    (``exact=False`` without the cache); ``subset``: the sorted flat indices of the only
    rays walked (numba, image only), whose rays ``scene`` holds (row ``i``: pixel
    ``subset[i]``, :func:`_segments_at`): they are walked as one row of their own, so the
    set-up and the walk cost what these rays cost, not the whole image.
    """
    nk, step, unit, lut, labmap, ids, memb, seg = scene
    k = len(spec.structures)
    cols, mats = _tables.material(spec)
    rs = spec.rendering
    light = _tables.light_array(camera, mats, rs.light_direction, rs.light_intensity)
    ratio = step / unit
    alpha_w = _tables.alpha_table(ids, memb, imp, ratio)
    alpha_r = _tables.alpha_table(ids, memb, ops, ratio)
    shade, has_curv = bool(rs.shade), curv is not None
    nrays = camera.width * camera.height
    idx = _grid.index_volume(volume, lut.lo, lut.scale, lut.size)
    cells = None if nk is None else _grid.cell_map(volume, idx, ids, memb, labmap)
    if shade:
        vol = _grid.voxel_records(volume, idx, cells)
        if cells is not None:  # the index lives on in the records only (numba's walk)
            idx = _grid.index_in_records(volume, idx, vol)
    else:  # the index, or the records that hold it (a view of them is not contiguous)
        vol = idx if cells is None else _grid.index_source(idx)
    cv = walk_curvature(curv, "numpy" if nk is None else kind)
    lab = (labmap, lut.size) if labmap is not None else (np.zeros((2, 2, 2), np.uint8), -1)
    tab = _tables.shading_table(light, k) if shade else np.zeros((1, 1, 2), np.uint16)
    args = (ids, alpha_r, cols, light, tab, shade, has_curv, _tables.ERT)
    walked = int(seg["n"].sum())
    lazy = None
    report(0.1)  # the derived volumes are ready; the walk follows
    # float64 accumulators come from reused scratch (fresh memory costs page faults); the
    # lock is held until _finish has copied them out
    locked = kind == "numba" and _SCRATCH_LOCK.acquire(blocking=False)
    try:
        if nk is None:
            out = _npk.walk(idx, *lab, cv, seg, step, ids, memb, alpha_w, has_curv, k, _tables.ERT)
            report(0.6)
            start, count = out["off"][:-1], np.diff(out["off"])
            c_lut, c_j, c_curv = out["lut"], out["steps"], out["curv"]
            c_sh = _npk.shade_entries(vol, seg, step, start, count, c_j, ids[c_lut], tab, shade)
            rgba, vis, cimg = _npk.composite(start, count, c_lut, c_sh, c_curv, *args, k)
            present, asg, aimp = out["present"], out["assigned"], out["importance_accumulated"]
            if skip:  # the full walk, stored as the skipping walk stores it
                asg = np.minimum(asg, _grid.SATURATION)
        else:
            walker = _walk_numba
            if kind == "cuda":
                walker = functools.partial(_walk_cuda, bg=np.asarray(spec.background, np.float32))
            walk_cam = camera if subset is None else _RayRow(len(subset))
            res = walker(nk, volume, lab, idx, vol, cv, seg, step, memb, alpha_w, args, k,
                         walk_cam, build_cache, occlusion_free, locked,
                         report.sub(0.1, 0.9), skip=skip)  # fmt: skip
            rgba, vis, asg, present, cimg, start, count, entries, walked, aimp = res
            if entries is not None:
                c_lut, c_j = entries["lut"], entries["steps"]
                c_sh, c_curv = entries["shading"], entries["curvature"]
        if build_cache:
            lazy = {
                "steps": c_j,
                "a": seg["a"],
                "b": seg["b"],
                "t": seg["t"],
                "step": float(step),
                "volume": vol,
                # the re-composite (numba, CPU) fills unset entries from the pages
                "curvature_volume": cv if nk is None else walk_curvature(curv, "numba"),
                "shading_key": _tables.shading_key(light, k) if shade else b"",
            }
        seconds = time.perf_counter() - t_start
        samples = int(seg["n"].sum())
        stats = {
            "rays": nrays,
            "rays_hit": int(np.count_nonzero(seg["n"])),
            "samples": samples,
            "samples_walked": walked,
            "samples_per_second": samples / seconds if seconds > 0 else 0.0,
            "seconds": seconds,
            "backend": kind,
            "sample_distance": step,
            "occlusion_free": bool(occlusion_free),
            "assigned_cap": _grid.SATURATION if skip else None,
            "params": _params(ops, cols, mats, rs.light_direction),
        }
        if not occlusion_free:  # not computed past early ray termination: no number at all
            asg = np.full((k, nrays), np.nan, np.float32)
            aimp = np.full(nrays, np.nan, np.float32)
        cache = None
        if build_cache:
            h, w = camera.height, camera.width
            cache = RayCache(
                spec=spec.with_opacities(ops),
                camera=camera,
                ids=ids,
                membership=memb,
                ratio=ratio,
                start=np.ascontiguousarray(start, np.int64),
                count=np.ascontiguousarray(count, np.int64),
                lut=c_lut,
                shading=c_sh,
                curvature=c_curv,
                assigned=np.asarray(asg, np.float32).reshape(k, h, w),
                present=np.asarray(present, np.uint32).reshape(h, w),
                backend=stats["backend"],
                stats=dict(stats),
                lazy=lazy,
                importance_accumulated=np.asarray(aimp, np.float32).reshape(h, w),
            )
            stats["cache_entries"] = len(c_lut)
            stats["cache_bytes"] = cache.nbytes
        if subset is not None:
            res = _finish_rays(subset, rgba, vis, asg, present, cimg, spec, camera, stats, aimp)
        elif isinstance(rgba, tuple):  # the GPU made the float32 outputs and the image
            res = _analysis(*rgba, vis, asg, present, cimg, spec, camera, stats, cache, aimp)
        else:
            res = _finish(rgba, vis, asg, present, cimg, spec, camera, stats, cache, aimp)
        report(1.0)
        return res
    finally:
        if locked:
            _SCRATCH_LOCK.release()


def _scene(volume: Volume, spec: StructureSpec, camera: Camera, backend: str,
           subset=None) -> tuple:  # fmt: skip
    """Backend, sample distance, unit, lookup table, label map, ids, membership and rays.

    ``subset``: the rays of these flat pixel indices only (:func:`_segments_at`, numba).
    """
    nk = _pick_backend(backend)
    step, unit = _tables.step_and_unit(spec, volume)
    lut = build_lut(spec, scalar_range=_grid.scalar_range(volume), dtype=volume.data.dtype)
    labmap, ids, memb = _with_labels(volume, spec, lut)
    if subset is not None:
        seg = _segments_at(nk, camera, volume, step, subset)
    elif _kind(backend, nk) == "cuda":  # the rays of a camera are made (and uploaded) once
        from dvr_perception.rays import _cuda

        pack = _grid.camera_pack(camera, volume, step)
        seg = _cuda.rays_for(pack, lambda: _segments(nk, camera, volume, step))
    else:
        seg = _segments(nk, camera, volume, step)
    return nk, step, unit, lut, labmap, ids, memb, seg


def _plan(volume, spec, camera, seg, lut, memb, curv, build_cache, memory_limit, brick):
    """:func:`~dvr_perception.rays.memory.plan` of one analysis (``curv``: the checked curvature).

    A whole-volume ``|H|`` array (dense or its pages, counted as dense) stays alive beside a
    bricked run too: the plan counts it.  ``curv`` may also be a bool (with curvature or
    not; not a whole array).
    """
    has = curv if isinstance(curv, bool) else curv is not None
    return memory.plan(
        volume, camera.width * camera.height, int(seg["n"].sum()), k=len(spec.structures),
        shade=bool(spec.rendering.shade), curvature=has, build_cache=build_cache,
        lut=lut, membership=memb, memory_limit=memory_limit, brick=brick,
        curvature_array=isinstance(curv, np.ndarray) or hasattr(curv, "kernel_arg"),
    )  # fmt: skip


def analyze_views(
    volume: Volume,
    spec: StructureSpec,
    cameras,
    *,
    curvature=None,
    build_cache: bool = False,
    memory_limit=None,
    progress=None,
    backend: str = "auto",
    exact: bool = False,
) -> list[RayAnalysis]:
    """:func:`analyze` for each camera; a volume analysed in bricks is read once for all.

    When every camera's analysis goes in bricks of one size (a large volume), the cameras
    that meet the bricks in the same order (one view at several resolutions) share a pass
    over the volume (:func:`~dvr_perception.rays.bricks.analyze_bricked_views`): each brick
    is derived once instead of once per camera.  The results equal separate calls.
    ``progress``: as :func:`analyze`, over all the cameras; ``exact``: as :func:`analyze`;
    ``backend``: as :func:`analyze`
    (the shared bricked pass is the CPU's: with ``"cuda"`` every camera is analysed whole on
    the GPU).

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> cams = [Camera.from_view(vol.bounds, width=n, height=n) for n in (16, 8)]
    >>> [a.image.shape for a in analyze_views(vol, spec, cams)]
    [(16, 16, 3), (8, 8, 3)]
    """
    cameras = list(cameras)
    if not cameras:
        raise DVRInputError("cameras: expected at least one camera")
    report = reporter(progress)
    curv = _check_curvature(curvature, volume)
    for cam in cameras:
        _check_inputs(volume, spec, cam, backend)
    # the tables and label map are the same for every camera: only the rays differ
    nk, step, _, lut, _, _, memb, _ = _scene(volume, spec, cameras[0], backend)
    segs = [_segments(nk, cam, volume, step) for cam in cameras]
    plans = [
        _plan(volume, spec, cam, seg, lut, memb, curv, build_cache, memory_limit, None)
        for cam, seg in zip(cameras, segs, strict=True)
    ]
    bricks = {tuple(p["brick"]) for p in plans if p["mode"] == "bricks"}
    shared = len(cameras) > 1 and len(bricks) == 1 and all(p["mode"] == "bricks" for p in plans)
    if shared and _kind(backend, nk) != "cuda":  # bricks are the CPU's (analyze() decides)
        from dvr_perception.rays.bricks import analyze_bricked_views

        results = analyze_bricked_views(
            volume, spec, cameras, brick=bricks.pop(), curvature=curv, build_cache=build_cache,
            memory_limit=memory_limit, progress=report, segments=segs, exact=exact,
        )  # fmt: skip
        return [_remember_source(r, volume, spec, backend, memory_limit) for r in results]
    kw = {
        "curvature": curvature,
        "build_cache": build_cache,
        "memory_limit": memory_limit,
        "backend": backend,
        "exact": exact,
    }
    n = len(cameras)
    return [analyze(volume, spec, cam, progress=report.sub(i / n, (i + 1) / n), **kw)
            for i, cam in enumerate(cameras)]  # fmt: skip


def can_rewalk(analysis) -> bool:
    """Whether :func:`rewalk` can render ``analysis``'s view again.

    True for an analysis :func:`analyze` made without a cache (it remembers its volume).
    """
    return isinstance(analysis, RayAnalysis) and analysis in _SOURCES


def rewalk(analysis: RayAnalysis, *, opacities, rays=None, background=None) -> RayAnalysis:
    """Render an analysis's view again with new opacities, walking the volume (no cache).

    What :func:`reevaluate` does from a cache, for an analysis made with
    ``build_cache=False``: the same volume, spec, camera and back end, the image only (rays
    stop at early ray termination), on ``rays`` only (flat pixel indices; default all).
    DECISIONS D7: the transparency of an enclosing layer reads what it covers re-composited
    without it; where no cache exists, this walk of the affected pixels with that layer's
    opacity 0 gives the same luminance as the cache's re-composite.

    Parameters
    ----------
    analysis : RayAnalysis
        Made by :func:`analyze` or :func:`analyze_views` with ``build_cache=False``.
    opacities : array_like of float
        ``K`` rendering opacities in [0, 1].
    rays : array_like of int, optional
        Flat pixel indices to walk (the others are background), as :func:`analyze`'s.
    background : array_like, optional
        RGB in [0, 1] behind the volume (default the spec's).

    Returns
    -------
    RayAnalysis
        ``occlusion_free=False``: ``assigned`` is NaN.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> cam = Camera.from_view(vol.bounds, width=8, height=8)
    >>> res = analyze(vol, spec, cam, build_cache=False)
    >>> ops = [s.render_opacity for s in spec.structures]
    >>> again = rewalk(res, opacities=ops, rays=[27, 28])
    >>> bool((again.image[3, 3:5] == res.image[3, 3:5]).all())
    True
    """
    volume, spec, backend, memory_limit = _source(analysis)
    spec = _with_background(spec, background)
    return analyze(volume, spec, analysis.camera, opacities=opacities, build_cache=False,
                   occlusion_free=False, rays=rays, backend=backend,
                   memory_limit=memory_limit)  # fmt: skip


def rewalk_rgba(analysis: RayAnalysis, variants) -> list[np.ndarray]:
    """:func:`rewalk`'s premultiplied colour for several opacity sets, each on its own rays.

    For each ``(opacities, rays)`` of ``variants``, the float32 ``(len(rays), 4)`` ``rgba``
    of ``rewalk(analysis, opacities=opacities, rays=rays)`` on those pixels, in ascending
    pixel order (``rays`` sorted, repeats dropped): the same numbers to the bit.  With numba
    and a whole-volume plan the variants are walked together, in one pass over the union of
    their rays (:func:`~dvr_perception.rays._numba_kernels.walk_variants`: every sample read
    once, each variant composited until its own early ray termination), and what no variant
    still walking a ray can see (blocks of structures of opacity 0 in them, e.g. an
    enclosing layer made transparent) is passed over.  Otherwise (numpy, a bricked plan)
    :func:`rewalk` is called per variant.  What DECISIONS D7's view without each enclosing
    layer needs, for all the enclosers of an analysis at once.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> cam = Camera.from_view(vol.bounds, width=8, height=8)
    >>> res = analyze(vol, spec, cam)
    >>> ops = [s.render_opacity for s in spec.structures]
    >>> both = rewalk_rgba(res, [(ops, [28, 27]), ([0.0] + ops[1:], [27])])
    >>> bool((both[0] == res.rgba[3, 3:5]).all()), both[1].shape
    (True, (1, 4))
    """
    t0 = time.perf_counter()
    out = _rewalk_rgba(analysis, variants)
    done = _RECOMPOSITES.setdefault(analysis, [])
    done.append({
        "layers": len(out),
        "rays": int(sum(len(v) for v in out)),
        "seconds": time.perf_counter() - t0,
        "bytes": int(sum(v.nbytes for v in out)),
    })  # fmt: skip
    return out


#: Per analysis, what :func:`rewalk_rgba` cost on it (:func:`recomposites`).
_RECOMPOSITES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def recomposites(analysis) -> list[dict]:
    """Return the walks :func:`rewalk_rgba` made of ``analysis``'s view without some layers.

    DECISIONS D7's extra cost of reading enclosing layers without a cache, one dict per call:
    ``layers`` (views walked), ``rays`` (pixels over all views), ``seconds`` and ``bytes``
    (the colours returned).  Empty for an analysis not walked again.
    """
    return [dict(r) for r in _RECOMPOSITES.get(analysis, ())]


def _source(analysis) -> tuple:
    """``(volume, spec, backend, memory_limit)`` :func:`analyze` made ``analysis`` from."""
    source = _SOURCES.get(analysis) if isinstance(analysis, RayAnalysis) else None
    if source is None:
        raise DVRInputError(
            "analysis: only an analysis made by analyze(..., build_cache=False) can be walked "
            "again (one with a cache re-composites with reevaluate)"
        )
    return source


def _rewalk_rgba(analysis, variants) -> list[np.ndarray]:
    volume, spec, backend, memory_limit = _source(analysis)
    camera = analysis.camera
    k = len(spec.structures)
    checked = [(_tables.check_opacities(ops, k), _checked_rays(rays, camera))
               for ops, rays in variants]  # fmt: skip
    nk = _pick_backend(backend)
    if not checked:
        return []
    mark = np.zeros(camera.width * camera.height, bool)  # (cheaper than np.unique)
    for _, rays in checked:
        mark[rays] = True
    union = np.flatnonzero(mark)
    plan = None
    if nk is not None:
        step, unit = _tables.step_and_unit(spec, volume)
        lut = build_lut(spec, scalar_range=_grid.scalar_range(volume), dtype=volume.data.dtype)
        labmap, ids, memb = _with_labels(volume, spec, lut)
        # the kernel sets up its rays itself; without a cache the plan needs no sample count
        none = {"n": np.zeros(1, np.int64)}
        plan = _plan(volume, spec, camera, none, lut, memb, False, False, memory_limit, None)
    if plan is None or plan["mode"] != "whole" or len(checked) > 63:
        alone = (rewalk(analysis, opacities=ops, rays=rays) for ops, rays in checked)
        return [np.ascontiguousarray(res.rgba.reshape(-1, 4)[rays])
                for res, (_, rays) in zip(alone, checked, strict=True)]  # fmt: skip
    rs = spec.rendering
    shade = bool(rs.shade)
    idx = _grid.index_volume(volume, lut.lo, lut.scale, lut.size)
    cells = _grid.cell_map(volume, idx, ids, memb, labmap)
    if shade:  # the volumes _analyze_whole derives (memoised on the volume)
        vol = _grid.voxel_records(volume, idx, cells)
        idx = _grid.index_in_records(volume, idx, vol)
    else:
        vol = _grid.index_source(idx)
    tix = _grid.compact_index(volume, idx)
    rep = _plateau_entries(ids, memb, k)
    t_bit = _tail_tables(ids, memb, np.zeros(len(ids)), rep, k)[3]
    lab = (labmap, lut.size) if labmap is not None else (np.zeros((2, 2, 2), np.uint8), -1)
    smask, sdist, _ = _grid.skip_maps(volume, tix, t_bit, labmap, lab[1], True, k)
    cols, mats = _tables.material(spec)
    light = _tables.light_array(camera, mats, rs.light_direction, rs.light_intensity)
    tab = _tables.shading_table(light, k) if shade else np.zeros((1, 1, 2), np.uint16)
    ratio = step / unit
    alpha_v = np.stack([_tables.alpha_table(ids, memb, ops, ratio) for ops, _ in checked])
    bit = np.where(memb > 0, np.left_shift(1, np.clip(ids, 0, 31)), 0).astype(np.uint64)
    visible = np.array([np.bitwise_or.reduce(np.where(al > 0.0, bit, 0)) for al in alpha_v],
                       np.uint64)  # fmt: skip
    want = np.zeros(len(union), np.uint64)
    rows = []
    for v, (_, rays) in enumerate(checked):
        pos = np.searchsorted(union, rays)
        want[pos] |= np.uint64(1) << np.uint64(v)
        rows.append(pos)
    rgba = np.empty((len(checked), len(union), 4), np.float32)
    nk.walk_variants(
        vol, cells, _grid.block_map(volume, cells), _grid.block_occupancy(volume, cells), rep,
        *lab, smask, sdist,
        _grid.camera_pack(camera, volume, step), union, step, want, ids, memb, alpha_v, visible,
        cols, light, tab, shade, _tables.ERT, rgba,
    )  # fmt: skip
    return [rgba[v, pos] for v, pos in enumerate(rows)]


def _with_background(spec: StructureSpec, background) -> StructureSpec:
    """``spec`` with ``background`` (checked RGB in [0, 1]) behind the volume; None: as is."""
    if background is None:
        return spec
    bg = np.asarray(background, dtype=np.float64)
    if bg.shape != (3,) or not np.all((bg >= 0) & (bg <= 1)):
        raise DVRInputError(f"background: expected 3 numbers in [0, 1], got {background}")
    return StructureSpec(spec.structures, tuple(bg), spec.rendering, spec.view, spec.labels_file)


_SCRATCH: dict = {}
_SCRATCH_LOCK = threading.Lock()


def _walk_numba(nk, volume, lab, idx, vol, cv, seg, step, memb, alpha_w, args, k, camera, build,
                tail, locked, report=None, skip=False):  # fmt: skip
    """Run the numba walk (with the cache: fused build and compositing, then compaction).

    ``skip``: the skipping walk behind early ray termination (``analyze(..., exact=False)``).
    """
    shade, has_curv = args[5], args[6]
    h, w = camera.height, camera.width
    nrays = h * w
    n = seg["n"]
    ids = args[0]
    tix = _grid.compact_index(volume, idx)
    cells = _grid.cell_map(volume, idx, ids, memb, lab[0] if lab[1] >= 0 else None)
    rep = _plateau_entries(ids, memb, k)
    order, chunk_ptr = ray_order(h, w)
    if report:
        order, chunk_ptr = _interleaved(order, chunk_ptr, _group())
    nchunk = len(chunk_ptr) - 1
    # every ray's outputs are written by the kernel: no zeroing needed
    rgba = _scratch("rgba", nrays, (4,), np.float64, locked)
    vis = _scratch("vis", k * nrays, (), np.float64, locked).reshape(k, nrays)
    # a spare last row: where the walk behind early ray termination counts empty samples
    asg_all = _scratch("asg", (k + 1) * nrays, (), np.float64, locked).reshape(k + 1, nrays)
    present = np.empty(nrays, np.uint32)
    cimg = _scratch("cimg", nrays, (), np.float64, locked)
    start = _scratch("start", nrays, (), np.int64, locked)  # with the cache: replaced by compact
    count = np.empty(nrays, np.int64) if build else _scratch("count", nrays, (), np.int64, locked)
    walked = _scratch("walked", nrays, (), np.int64, locked)
    aimp = _scratch("aimp", nrays, (), np.float64, locked)
    per_chunk = np.add.reduceat(n[order].astype(np.int64), chunk_ptr[:-1])
    chunk_base = np.concatenate([[0], np.cumsum(per_chunk)])
    total = int(chunk_base[-1]) if build else 1
    chunk_base = np.ascontiguousarray(chunk_base[:-1])
    chunk_end = np.zeros(nchunk, np.int64)
    cap = max(total, 1)
    # the entries' regions are filled in part: only the pages written take memory
    src_lut = _scratch("lut", cap, (), np.uint16, locked, sparse=True)
    src_j = _scratch("j", cap if build else 1, (), np.int32, locked, sparse=True)
    src_sh = _scratch("sh", cap if build and shade else 1, (2,), np.uint16, locked, sparse=True)
    src_curv = _scratch("curv", cap if build and has_curv else 1, (), np.float32, locked,
                        sparse=True)  # fmt: skip
    tail_tables = _tail_tables(ids, memb, alpha_w, rep, k)
    labels = lab[0] if lab[1] >= 0 else None
    maps = (tix, cells, _grid.block_map(volume, cells), _grid.block_occupancy(volume, cells), rep,
            *lab, *tail_tables,
            *_grid.skip_maps(volume, tix, tail_tables[3], labels, lab[1], skip, k))  # fmt: skip
    layout = (order, chunk_ptr, h, w)
    out = _walk_compact(nk, vol, maps, cv, seg, step, layout, memb, alpha_w, args,
                        (build, tail), chunk_base, rgba, vis, asg_all, present, cimg, src_lut,
                        src_j, src_sh, src_curv, start, count, chunk_end, walked, aimp,
                        _scratch("state", nrays, (7,), np.float64, locked), report)  # fmt: skip
    return (out[0], out[1], asg_all[:k], *out[3:], aimp)


def _walk_cuda(nk, volume, lab, idx, vol, cv, seg, step, memb, alpha_w, args, k, camera, build,
               tail, locked=False, report=None, bg=None, skip=False):  # fmt: skip
    """Run the walk on the GPU (:mod:`~dvr_perception.rays._cuda_kernels`); as :func:`_walk_numba`.

    One thread per ray.  The float32 outputs and the image over the background ``bg`` are
    made on the device: ``rgba`` comes back as ``(rgba, image, accumulated)``, ``vis``,
    ``cimg``, ``asg`` and ``aimp`` as float32 (``asg`` and ``aimp`` not at all without
    ``tail``: analyze() gives NaN there), the walked samples as their sum.  With ``build``
    every ray packs its cache entries into a region of its own (its sample count: an upper
    bound), then the entries are packed in row-major pixel order on the device and copied
    back: the same cache as the CPU engine's.

    What does not change between analyses stays on the device: the derived volumes while the
    volume lives, the rays of the last cameras (:func:`_cuda.rays_for`), the small tables by
    content (:func:`_cuda.table`) and the per-ray work arrays (:func:`_cuda.scratch`, while no
    other analysis holds them).
    """
    from dvr_perception.rays import _cuda

    ck = _cuda.kernels()
    ids, alpha_r, cols, light, tab, shade, has_curv, ert = args
    h, w = camera.height, camera.width
    nrays = h * w
    n = np.ascontiguousarray(seg["n"])
    tix = _grid.compact_index(volume, idx)
    cells = _grid.cell_map(volume, idx, ids, memb, lab[0] if lab[1] >= 0 else None)
    blocks = _grid.block_map(volume, cells)
    occ = _grid.block_occupancy(volume, cells)
    rep = _plateau_entries(ids, memb, k)
    kmap, tids, t_alpha, t_bit = _tail_tables(ids, memb, alpha_w, rep, k)
    smask, sdist, cap_ = _grid.skip_maps(volume, tix, t_bit, lab[0] if lab[1] >= 0 else None,
                                         lab[1], skip, k)  # fmt: skip
    cached = "total" in seg  # a ray set of _cuda.rays_for: kept on the device
    total = seg["total"] if cached else int(n.sum())
    cap = max(total, 1) if build else 1
    big = (vol, tix, cells, blocks, occ, lab[0], cv)
    entry = 2 + 4 + (4 if shade else 0) + (4 if has_curv else 0)
    need = sum(a.nbytes for a in big) + nrays * 8 * (2 * k + 25) + (cap * entry if build else 0)
    _cuda.check_fits(int(need * 1.1) + (2 * cap * entry if build else 0))
    # the placeholders of no curvature or labels are new arrays each time: kept by content
    dev = [_cuda.table(a) if a.nbytes <= 1 << 16 else _cuda.to_device(a, keep=True) for a in big]
    small = [_cuda.table(a) for a in (rep, kmap, tids, t_alpha, t_bit)]
    smask_d, sdist_d = (_cuda.table(a) if a.nbytes <= 1 << 16 else _cuda.to_device(a, keep=True)
                        for a in (smask, sdist))  # fmt: skip
    if cached:
        rays = [_cuda.to_device(seg[q], keep=True, pool="rays") for q in ("a", "b", "t", "n")]
    else:
        rays = [_cuda.to_device(seg[q]) for q in ("a", "b", "t")] + [_cuda.to_device(n)]
    if build:
        base = seg.get("base")
        if base is None:
            base = np.zeros(nrays, np.int64)
            np.cumsum(n[:-1], out=base[1:])
            if cached:
                seg["base"] = base  # the camera's next cache builds reuse it
        base_d = _cuda.to_device(base, keep=cached, pool="rays")
    else:  # read by the walk only with build: any int64 array of nrays will do (below)
        base_d = None
    tables = [_cuda.table(a) for a in (ids, memb, alpha_r, alpha_w, cols, light, tab)]
    mine = _cuda.WORK_LOCK.acquire(blocking=False)
    try:

        def buf(name, shape, dtype):
            return _cuda.scratch(name, shape, dtype, mine)

        out = {
            "rgba": buf("rgba", (nrays, 4), np.float64),
            "vis": buf("vis", (k, nrays), np.float64),
            "asg": buf("asg", (k + 1, nrays), np.float64),
            "present": buf("present", nrays, np.uint32),
            "cimg": buf("cimg", nrays, np.float64),
            "count": buf("count", nrays, np.int64),
            "walked": buf("walked", nrays, np.int64),
            "aimp": buf("aimp", nrays, np.float64),
            "state": buf("state", (nrays, 7), np.float64),
        }
        if base_d is None:
            base_d = out["count"]  # never read without build (_walk_ray packs nothing)
        src = (
            buf("src_lut", cap, np.uint16),
            buf("src_j", cap, np.int32),
            buf("src_sh", (cap if build and shade else 1, 2), np.uint16),
            buf("src_curv", cap if build and has_curv else 1, np.float32),
        )
        bx, by = ck.BLOCK
        grid = (-(-w // bx), -(-h // by))
        vol_d, tix_d, cells_d, blocks_d, occ_d, lab_d, cv_d = dev
        with _cuda.quiet_launch():  # small images: no low-occupancy warning per frame
            ck.walk[grid, (bx, by)](
                vol_d, tix_d, cells_d, blocks_d, occ_d, small[0], lab_d, np.int64(lab[1]),
                *small[1:], smask_d, sdist_d, float(cap_), cv_d, *rays, base_d, float(step),
                *tables, bool(shade), bool(has_curv), bool(build), bool(tail), float(ert),
                out["rgba"], out["vis"], out["asg"], out["present"], out["cimg"], out["count"],
                out["walked"], out["aimp"], out["state"], *src, np.int64(w), np.int64(h),
            )  # fmt: skip
        # float32 outputs and the image over the background made on the device (as _finish)
        fin = {
            "rgba": buf("f_rgba", (nrays, 4), np.float32),
            "image": buf("f_image", (nrays, 3), np.float32),
            "acc": buf("f_acc", nrays, np.float32),
            "vis": buf("f_vis", (k, nrays), np.float32),
            "cimg": buf("f_cimg", nrays, np.float32),
            "asg": buf("f_asg", (k, nrays), np.float32),
            "aimp": buf("f_aimp", nrays, np.float32),
        }
        walked_d = buf("walked_sum", 1, np.int64)
        walked_d.copy_to_device(np.zeros(1, np.int64))
        threads = 128
        with _cuda.quiet_launch():
            ck.finish[-(-nrays // threads), threads](
                out["rgba"], out["vis"], out["cimg"], out["asg"], out["aimp"], out["walked"],
                _cuda.table(bg), fin["rgba"], fin["image"], fin["acc"], fin["vis"],
                fin["cimg"], fin["asg"], fin["aimp"], walked_d,
            )  # fmt: skip
        wanted = ("rgba", "image", "acc", "vis", "cimg") + (("asg", "aimp") if tail else ())
        host = {q: fin[q].copy_to_host() for q in wanted}
        host["present"] = out["present"].copy_to_host()
        walked = int(walked_d.copy_to_host()[0])
        if report:
            report(0.9)
        start, count, entries = None, None, None
        if build:
            count = out["count"].copy_to_host()
            start = np.zeros(nrays, np.int64)
            np.cumsum(count[:-1], out=start[1:])
            e = int(start[-1] + count[-1]) if nrays else 0
            m = max(e, 1)
            dst = (
                _cuda_array(m, np.uint16),
                _cuda_array(m, np.int32),
                _cuda_array((m if shade else 1, 2), np.uint16),
                _cuda_array(m if has_curv else 1, np.float32),
            )
            with _cuda.quiet_launch():
                ck.compact[-(-nrays // threads), threads](
                    base_d, out["count"], _cuda.to_device(start), *src, *dst,
                    bool(shade), bool(has_curv),
                )  # fmt: skip
            lut_h, j_h, sh_h, curv_h = (d.copy_to_host() for d in dst)
            entries = {
                "lut": lut_h[:e],
                "steps": j_h[:e],
                "shading": sh_h[: e if shade else 0],
                "curvature": curv_h[: e if has_curv else 0],
            }
    finally:
        if mine:
            _cuda.WORK_LOCK.release()
    rgba = (host["rgba"], host["image"], host["acc"])  # finished: see analyze()
    return (rgba, host["vis"], host.get("asg"), host["present"], host["cimg"], start, count,
            entries, walked, host.get("aimp"))  # fmt: skip


def _cuda_array(shape, dtype):
    """Return a new device array (``numba.cuda.device_array``)."""
    from numba import cuda

    return cuda.device_array(shape, dtype)


def _scratch(name, n, tail, dtype, shared, sparse=False):
    """Return ``n`` rows of a reusable module-level scratch array.

    Page faults of fresh memory cost several ms per frame.  ``shared`` False (another thread
    holds the scratch lock): a private array.  ``sparse``: memory of which the walk writes
    only a part (:func:`~dvr_perception.rays._grid.sparse_zeros`).
    """
    make = _grid.sparse_zeros if sparse else np.empty
    if not shared:
        return make((n, *tail), dtype)
    a = _SCRATCH.get(name)
    if a is None or len(a) < n:
        _SCRATCH.pop(name, None)  # freed before the larger one is made
        a = make((max(n, int(1.25 * len(a)) if a is not None else n), *tail), dtype)
        _SCRATCH[name] = a
    return a[:n]


def release_scratch(*, scratch: bool = True) -> None:
    """Give memory back: the walk's scratch (``scratch``) and the C heap's free memory.

    The scratch (kept to spare the next analysis page faults: the per-ray buffers and the
    cache-building walk's entries, about the size of the largest cache built) is for a
    caller that walks no more rays for a while (the optimiser, once its views are
    analysed); it is skipped while an analysis holds it.  The C library is asked to return
    the heap memory that earlier analyses and measures freed (glibc's ``malloc_trim``: 85 MiB
    after the timed frames of a 512 x 512 x 452 CT), e.g. before a large analysis.
    """
    if scratch and _SCRATCH_LOCK.acquire(blocking=False):
        try:
            _SCRATCH.clear()
        finally:
            _SCRATCH_LOCK.release()
    _trim_heap()


@functools.cache
def _malloc_trim():
    """Return glibc's ``malloc_trim``, or None (another C library, or none found)."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


def _trim_heap() -> None:
    """Return the C heap's free memory to the system where the C library can (glibc)."""
    fn = _malloc_trim()
    if fn is not None:
        fn(0)


def _walk_compact(nk, vol, maps, cv, seg, step, layout, memb, alpha_w, args, modes,
                  chunk_base, rgba, vis, asg, present, cimg, src_lut, src_j, src_sh, src_curv,
                  start, count, chunk_end, walked, aimp, state, report=None):  # fmt: skip
    ids, alpha_r, cols, light, tab, shade, has_curv, ert = args
    build, tail = modes
    n = seg["n"]
    order, chunk_ptr, h, w = layout
    nchunk = len(chunk_ptr) - 1
    # with a progress callback the chunks go in groups (one kernel call each, the same work
    # per ray: the result does not change), reported between the calls
    per = _group() if report else nchunk
    for c0 in range(0, nchunk, per):
        c1 = min(c0 + per, nchunk)
        nk.walk(
            vol, *maps, cv, seg["a"], seg["b"], seg["t"], n, step, order, chunk_ptr[c0 : c1 + 1],
            c1 - c0, ids, memb, alpha_r, alpha_w, cols, light, tab, shade, has_curv, build, tail,
            chunk_base[c0:c1], ert, rgba, vis, asg, present, cimg, src_lut, src_j, src_sh,
            src_curv, start, count, chunk_end[c0:c1], walked, aimp, state,
        )  # fmt: skip
        if report:
            report(c1 / nchunk)
    entries = None
    if build:
        # entries move to row-major pixel order, the order compositing reads them in
        dest = np.empty(len(count), np.int64)
        dest[0] = 0
        np.cumsum(count[:-1], out=dest[1:])
        e = int(dest[-1] + count[-1])
        entries = {
            "lut": np.empty(e, np.uint16),
            "steps": np.empty(e, np.int32),
            "shading": np.empty((e if shade else 0, 2), np.uint16),
            "curvature": np.empty(e if has_curv else 0, np.float32),
        }
        rows, row_ptr = ray_order(h, w, tile=(1, w))
        nk.compact(
            rows, row_ptr, len(row_ptr) - 1, start, count, dest, src_lut, src_j, src_sh, src_curv,
            entries["lut"], entries["steps"], entries["shading"], entries["curvature"], shade,
            has_curv,
        )  # fmt: skip
        start = dest
    return rgba, vis, asg, present, cimg, start, count, entries, int(walked.sum())


def _subset_order(rays, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the visiting order of the flat pixel indices ``rays`` and its chunk pointers.

    The indices sorted and unique, in at most :data:`_CHUNKS` chunks of consecutive runs
    (as :func:`ray_order`'s ``(order, chunk_ptr)``).
    """
    try:
        order = np.array(rays, np.int64).ravel()  # a copy: made read-only below
    except (TypeError, ValueError):
        raise DVRInputError("rays: expected flat pixel indices") from None
    if order.size > 1 and not np.all(order[1:] > order[:-1]):  # flatnonzero's already are
        order = np.unique(order)
    if order.size and (order[0] < 0 or order[-1] >= n):
        raise DVRInputError(f"rays: expected flat pixel indices in [0, {n}), got {rays!r}")
    nchunk = max(min(order.size // 16, _CHUNKS), 1)
    chunk_ptr = (np.arange(nchunk + 1, dtype=np.int64) * order.size) // nchunk
    order.flags.writeable = False  # typed as ray_order's (no second compilation)
    chunk_ptr.flags.writeable = False
    return order, chunk_ptr


def _lighting(z: dict, camera, mats, direction, intensity, shade: bool, k: int) -> tuple:
    """``(light, shading table, shading key)`` of a re-evaluation, the latest one kept in ``z``.

    The same materials, light direction and intensity for the same cache (one camera) give
    the same arrays: the transparency measure re-composites a rendering several times
    (without each enclosing layer) with its lighting unchanged.
    """
    try:  # the bits of every number (0.0 and -0.0 differ)
        d = np.asarray(direction, np.float64)
        m = [(x.ambient, x.diffuse, x.specular, x.specular_power) for x in mats]
        memo_key = (np.array(m, np.float64).tobytes(), d.tobytes(), d.shape,
                    np.float64(intensity).tobytes(), shade, k)  # fmt: skip
    except (TypeError, ValueError, AttributeError):
        memo_key = None  # light_array says what is wrong
    hit = z.get("lighting_memo")
    if memo_key is not None and hit is not None and hit[0] == memo_key:
        return hit[1]
    light = _tables.light_array(camera, mats, direction, intensity)
    tab = _tables.shading_table(light, k) if shade else np.zeros((1, 1, 2), np.uint16)
    out = (light, tab, _tables.shading_key(light, k) if shade else b"")
    if memo_key is not None:
        z["lighting_memo"] = (memo_key, out)
    return out


def _refresh_shading(cache: RayCache, nk, tab: np.ndarray, key, shade: bool) -> None:
    """Bring the cached shading up to a change of light or specular powers.

    ``key`` is the new shading key (:func:`_lighting`); nothing is done when it is the
    cache's own.  ``nk``: the numba kernels (entries marked, shaded again on first use), or
    None for a numpy cache (every entry shaded again here).
    """
    z = cache.lazy
    if key == z["shading_key"]:
        return
    if nk is None:
        seg = {"a": z["a"], "b": z["b"], "t": z["t"]}
        cache.shading[:] = _npk.shade_entries(
            z["volume"], seg, z["step"], cache.start, cache.count, z["steps"],
            cache.ids[cache.lut], tab, shade,
        )  # fmt: skip
    else:
        # specular powers alone changed: only those structures' entries are recomputed
        stale = None if z.get("refill") else _tables.stale_structures(z["shading_key"], key)
        with serial_below(len(cache.shading)):
            if stale is None:
                nk.invalidate(cache.shading)
            else:
                nk.invalidate_structures(cache.shading, cache.lut, cache.ids, stale)
        if z.get("fill") is not None:  # a lazily shaded bricked cache: shaded below
            z["filled"] = None
        elif z.get("refill") is not None:  # a bricked cache: no whole volume to fill from
            z["refill"](cache, tab)
    z["shading_key"] = key


@renamed_keyword("colors", "colours")
def reevaluate(
    cache: RayCache,
    *,
    opacities=None,
    lighting=None,
    colours=None,
    light_direction=None,
    background=None,
    rays=None,
) -> RayAnalysis:
    """Re-composite a cached analysis with new opacities, materials, light or background.

    Only the cached per-ray sample lists are walked (with early ray termination at the new
    opacities); the volume is not sampled again, except for the shading and curvature of
    entries that no earlier compositing reached (numba backend: computed once, on first use)
    and for the shading of all entries after a change of light direction or specular power.
    ``assigned`` and ``present`` do not depend on these parameters and are taken from the
    cache.  The cache of a ``backend="cuda"`` analysis (entries built on the GPU, equal to
    the CPU's) re-composites here on the CPU, with numba.  Unspecified parameters keep the
    values of
    the :func:`analyze` call that built the cache.

    Parameters
    ----------
    cache : RayCache
        ``analyze(..., build_cache=True).cache``.
    opacities : array_like of float, optional
        ``K`` rendering opacities in [0, 1].
    lighting : sequence of Lighting, optional
        ``K`` per-structure materials.
    colours : array_like, optional
        ``(K, 3)`` RGB in [0, 1] (``colors=`` is a deprecated alias).
    light_direction : array_like, optional
        Light direction in camera coordinates (``(0, 0, 1)`` = headlight).
    background : array_like, optional
        RGB in [0, 1] behind the volume.
    rays : array_like of int, optional
        Flat pixel indices: re-composite only these rays (numba and cuda caches; each equal
        to the whole image's to the last bit).  The other pixels hold zeros (the background's
        colour in ``image``): a partial view, for measures that read only these pixels (the
        view without an enclosing layer of :func:`~dvr_perception.measures.transparency`).

    Returns
    -------
    RayAnalysis
        With ``cache`` set to the same cache.
    """
    t_start = time.perf_counter()
    if not isinstance(cache, RayCache):
        raise DVRInputError(
            f"cache: expected the RayCache of analyze(..., build_cache=True), "
            f"got {type(cache).__name__}"
        )
    spec, camera = cache.spec, cache.camera
    k = len(spec.structures)
    ops = _tables.check_opacities(
        [s.render_opacity for s in spec.structures] if opacities is None else opacities, k
    )
    cols, mats = _tables.material(spec, colours=colours, lighting=lighting)
    rs = spec.rendering
    direction = rs.light_direction if light_direction is None else light_direction
    spec = _with_background(spec, background)
    alpha_r = _tables.alpha_table(cache.ids, cache.membership, ops, cache.ratio)
    shade = bool(rs.shade)
    has_curv = cache.curvature.size > 0
    z = cache.lazy
    light, tab, key = _lighting(z, camera, mats, direction, rs.light_intensity, shade, k)
    args = (cache.ids, alpha_r, cols, light, tab, shade, has_curv, _tables.ERT)
    h, w = camera.height, camera.width
    nk = _numba_kernels() if cache.backend in ("numba", "cuda") else None
    _refresh_shading(cache, nk, tab, key, shade)  # new light or specular powers
    if nk is not None and z.get("fill") is not None:  # what compositing can reach is shaded
        z["fill"](cache, alpha_r, tab)
    if nk is None:
        rgba, vis, cimg = _npk.composite(
            cache.start, cache.count, cache.lut, cache.shading, cache.curvature, *args, k
        )
    else:  # the kernel writes the float32 results itself
        alloc = np.empty if rays is None else np.zeros  # a partial view: zeros elsewhere
        out = (
            np.asarray(spec.background, np.float32),
            alloc((h * w, 4), np.float32),
            alloc((h * w, 3), np.float32),
            alloc(h * w, np.float32),
            alloc((k, h * w), np.float32),
            alloc(h * w, np.float32),
        )
        if rays is None:
            order, chunk_ptr = ray_order(h, w, tile=(1, w))
            work = len(cache.lut)
        else:
            order, chunk_ptr = _subset_order(rays, h * w)
            out[2][:] = np.clip(out[0], 0.0, 1.0)
            work = int(cache.count[order].sum())
        _composite(nk, cache, order, chunk_ptr, work, alpha_r, cols, light, tab, shade, out)
        stats = {"backend": cache.backend, "rays": h * w, "reevaluated": True}
        if rays is not None:
            stats.update(rays=len(order), partial=True)
        stats["params"] = _params(ops, cols, mats, direction)
        stats["cache_entries"] = len(cache.lut)
        res = _analysis(*out[1:4], out[4], cache.assigned, cache.present, out[5], spec, camera,
                        stats, cache, cache.importance_accumulated)  # fmt: skip
        stats["seconds"] = time.perf_counter() - t_start
        return res
    seconds = time.perf_counter() - t_start
    stats = {"seconds": seconds, "backend": cache.backend, "rays": h * w, "reevaluated": True}
    stats["params"] = _params(ops, cols, mats, direction)
    stats["cache_entries"] = len(cache.lut)
    return _finish(
        rgba,
        vis,
        cache.assigned,
        cache.present,
        cimg,
        spec,
        camera,
        stats,
        cache,
        cache.importance_accumulated,
    )


def _composite(nk, cache, order, chunk_ptr, work, alpha_r, cols, light, tab, shade, out):
    """Composite ``cache``'s entries of the rays ``order`` into ``out`` (numba kernel).

    ``work``: the entries composited; few run on the calling thread (numba's threads cost
    more than they save).
    """
    z = cache.lazy
    with serial_below(work):
        nk.composite(
            cache.start, cache.count, cache.lut, z["steps"], cache.shading,
            cache.curvature, z["a"], z["b"], z["t"], z["step"], z["volume"],
            z["curvature_volume"], order, chunk_ptr, len(chunk_ptr) - 1, cache.ids, alpha_r,
            cols, light, tab, shade, cache.curvature.size > 0, _tables.ERT, out,
        )  # fmt: skip


def reevaluate_rgba(
    cache: RayCache, variants, *, lighting=None, colours=None, light_direction=None
) -> list[np.ndarray]:
    """:func:`reevaluate`'s premultiplied colour for several opacity sets, each on its own rays.

    For each ``(opacities, rays)`` of ``variants``, the float32 ``(len(rays), 4)`` ``rgba``
    of ``reevaluate(cache, opacities=opacities, rays=rays, ...)`` on those pixels, in
    ascending pixel order (``rays`` sorted, repeats dropped): the same numbers to the bit.
    The materials, colours and light (as :func:`reevaluate`'s) are set up once for all the
    variants; each is then composited from the cache on its own rays.  What DECISIONS D7's
    view without each enclosing layer needs, for all the enclosers of a cached analysis at
    once (the optimiser's renderings).

    Parameters
    ----------
    cache : RayCache
        ``analyze(..., build_cache=True).cache`` of the numba or cuda backend.
    variants : sequence of (array_like, array_like)
        ``(opacities, rays)``: ``K`` rendering opacities and flat pixel indices.
    lighting, colours, light_direction : optional
        As :func:`reevaluate`'s, shared by every variant.

    Returns
    -------
    list of numpy.ndarray
        One float32 ``(n, 4)`` array per variant.

    Raises
    ------
    DVRInputError
        If ``cache`` is not a numba or cuda :class:`RayCache`, or a variant's opacities or
        rays are not valid.

    Examples
    --------
    >>> from dvr_perception.structures.phantom import make_phantom
    >>> vol, spec = make_phantom(size=24)
    >>> cam = Camera.from_view(vol.bounds, width=8, height=8)
    >>> res = analyze(vol, spec, cam, build_cache=True)
    >>> ops = [s.render_opacity for s in spec.structures]
    >>> both = reevaluate_rgba(res.cache, [(ops, [28, 27]), ([0.0] + ops[1:], [27])])
    >>> bool((both[0] == res.rgba[3, 3:5]).all()), both[1].shape
    (True, (1, 4))
    """
    if not isinstance(cache, RayCache) or cache.backend not in ("numba", "cuda"):
        raise DVRInputError(
            "cache: expected the numba or cuda RayCache of analyze(..., build_cache=True), "
            f"got {type(cache).__name__}"
        )
    spec, camera = cache.spec, cache.camera
    k = len(spec.structures)
    cols, mats = _tables.material(spec, colours=colours, lighting=lighting)
    rs = spec.rendering
    direction = rs.light_direction if light_direction is None else light_direction
    shade = bool(rs.shade)
    z = cache.lazy
    light, tab, key = _lighting(z, camera, mats, direction, rs.light_intensity, shade, k)
    nk = _numba_kernels()
    _refresh_shading(cache, nk, tab, key, shade)
    n = camera.height * camera.width
    bg = np.asarray(spec.background, np.float32)
    got = []
    for opacities, rays in variants:
        ops = _tables.check_opacities(opacities, k)
        order, chunk_ptr = _subset_order(rays, n)
        alpha_r = _tables.alpha_table(cache.ids, cache.membership, ops, cache.ratio)
        if z.get("fill") is not None:  # what compositing can reach is shaded
            z["fill"](cache, alpha_r, tab)
        out = (bg, np.zeros((n, 4), np.float32), np.zeros((n, 3), np.float32),
               np.zeros(n, np.float32), np.zeros((k, n), np.float32),
               np.zeros(n, np.float32))  # fmt: skip
        work = int(cache.count[order].sum())
        _composite(nk, cache, order, chunk_ptr, work, alpha_r, cols, light, tab, shade, out)
        got.append(out[1][order])
    return got
