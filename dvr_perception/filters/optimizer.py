"""``TransferFunctionOptimizer``: optimise a volume's rendering parameters inside a VTK pipeline.

One 3-D ``vtkImageData`` in; one 2-D ``vtkImageData`` out: the rendering of the **optimised**
spec, with exactly the point and field data of
:class:`~dvr_perception.filters.PerceptionMeasures` (``rgba``, ``luminance``, the three
deviation maps, ``layer_set``, ``region_id``; ``E_v``, ``E_s``, ``E_t``, ``structure_names``,
``visible_share``, ``target_share``, ``assigned_share``, ``perceived_transparency``,
``expected_opacity``).  The
filter runs :func:`~dvr_perception.optimize.optimize` and then measures the optimised spec
with the library measures at the output resolution, on the optimiser's own rendering of the
view (``OptimizationResult.analyses``: equal to a fresh analysis, plus the re-evaluation cache
the transparency measure reads where an enclosing layer's plain view is missing), as
``dvr-perception optimize`` does; without a region and with one view the ``E_*`` arrays equal
the optimiser's ``final`` terms.

The optimised parameters are **field-data arrays** of the same output (one port keeps the
filter a plain image filter in ParaView; a ``vtkTable`` can be made from them with
*Field Data to Table*).  Ordered like ``structure_names``, one tuple per structure:

``opacity``
    the optimised rendering opacity;
``color`` (3 components)
    RGB in [0, 1];
``ambient``, ``diffuse``, ``specular``, ``specular_power``
    the material.

One tuple each: ``light_direction`` (3 components, camera coordinates), ``E`` (the weighted
sum of Eq. 12 with ``weights``), ``initial_E_v``, ``initial_E_s``, ``initial_E_t``,
``initial_E`` (the optimiser's whole-image terms before), ``status`` (0 converged, 1 stopped,
2 a stage hit ``max_iter``; see :data:`~dvr_perception.optimize.STATUS_MESSAGES`),
``iterations``; and the strings ``optimized_spec_json`` (the optimised spec as JSON, the format of
:func:`~dvr_perception.structures.io.spec_to_dict`) and ``status_message``; and ``why``, one
line per structure: its opacity and share of the picture before -> target -> after and the
optimiser's reason in words (:func:`~dvr_perception.optimize.explain.explain`); per structure
also ``opacity_before`` and ``share_before`` (the numbers of those lines before the
optimisation), and one tuple ``opacity_unit_distance`` (the spec's, else the smallest voxel
spacing: the value a ParaView volume display needs to match the engine's opacity).  With a
``region`` (the lens) also ``lens_region`` (the lens as a string) and, one tuple each,
``lens_initial_E_v`` ... ``lens_initial_E`` and ``lens_E_v`` ... ``lens_E``: the optimiser's
terms inside the lens before and after (what it minimised).

Progress is reported with ``UpdateProgress``: the curvature volume and the first ray analyses
from inside (0 to 0.2, :meth:`~dvr_perception.filters._base.DVRFilterBase.progress_range`),
then the optimiser's callback (0.2 to 0.9 over the expected iterations).  ``AbortExecute``
(ParaView's *Abort*) stops the optimiser after the current iteration with the best parameters
so far (during the preparation: the filter fails with a "cancelled" error).  Errors are
reported through VTK's error mechanism (see :mod:`dvr_perception.filters._base`).
"""

from __future__ import annotations

import json
import math

import numpy as np

from dvr_perception.errors import DVRInputError
from dvr_perception.filters._base import (
    Parameter,
    as_positive_int,
    double_array,
    engine_luminance,
    point_array,
    string_array,
)
from dvr_perception.filters.perception_measures import PerceptionMeasures, _nan, _rows_up
from dvr_perception.measures import shape, transparency, visibility
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import attach_labels, check_spec_for_volume, spec_to_dict

__all__ = ["TransferFunctionOptimizer"]

_TERMS = ("E_v", "E_s", "E_t")


def as_stages(value, name: str) -> tuple[str, ...]:
    """Accept a comma-separated string or a sequence of stage names of the registry."""
    from dvr_perception.optimize import STAGES

    items = value.split(",") if isinstance(value, str) else value
    try:
        stages = tuple(str(s).strip() for s in items)
    except TypeError:
        raise DVRInputError(f"{name}: expected stage names, got {value!r}") from None
    unknown = [s for s in stages if s not in STAGES]
    if not stages or unknown:
        raise DVRInputError(
            f"{name}: unknown or missing stage(s) {unknown or value!r}; known: {', '.join(STAGES)}"
        )
    return stages


def as_weights(value, name: str) -> tuple[float, float, float]:
    """Accept three finite numbers >= 0, not all zero (``w_v, w_s, w_t``)."""
    try:
        w = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        w = ()
    if len(w) != 3 or not all(math.isfinite(v) and v >= 0 for v in w) or max(w) <= 0:
        raise DVRInputError(
            f"{name}: expected three numbers (w_v, w_s, w_t) >= 0, not all zero, got {value!r}"
        )
    return w


def as_seed(value, name: str) -> int:
    """Accept an integer >= 0."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        try:
            ok = int(value) == value and int(value) >= 0 and not isinstance(value, bool)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise DVRInputError(f"{name}: expected an integer >= 0, got {value!r}")
    return int(value)


def as_resolution(value, name: str) -> int:
    """Accept 0 (the optimiser's default) or an integer >= 8."""
    if value in (0, None):
        return 0
    v = as_positive_int(value, name)
    if v < 8:
        raise DVRInputError(f"{name}: expected 0 (default) or an integer >= 8, got {value!r}")
    return v


def as_region(value, name: str):
    """Accept ``""``/``None`` (whole image), ``"rect,x0,y0,x1,y1"`` or ``"circle,cx,cy,r"``.

    Numbers are output-image pixels (x right, y down from the top-left corner, as
    :func:`dvr_perception.optimize.optimize`'s ``region``); a sequence such as
    ``("rect", 0, 0, 10, 10)`` is accepted too.  Whether the shape covers any pixel is checked
    when the filter runs (it depends on ``width`` and ``height``).

    Examples
    --------
    >>> as_region("circle, 32, 32, 10", "region")
    ('circle', 32.0, 32.0, 10.0)
    >>> as_region("", "region") is None
    True
    """
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    items = [v.strip() for v in value.split(",")] if isinstance(value, str) else list(value)
    kind = str(items[0]).strip().lower() if items else ""
    sizes = {"rect": 4, "circle": 3}
    try:
        nums = tuple(float(v) for v in items[1:])
    except (TypeError, ValueError):
        nums = ()
    if kind not in sizes or len(nums) != sizes[kind] or not all(map(math.isfinite, nums)):
        raise DVRInputError(
            f"{name}: expected '' (whole image), 'rect,x0,y0,x1,y1' or 'circle,cx,cy,r' in "
            f"output pixels, got {value!r}"
        )
    return (kind, *nums)


def _region_text(region) -> str:
    """Spell the lens as the ``Region`` property does (``"rect,4,4,16,12"``).

    >>> _region_text(("rect", 4.0, 4.0, 16.0, 12.5))
    'rect,4,4,16,12.5'
    """
    return ",".join([region[0], *(f"{v:g}" for v in region[1:])])


class TransferFunctionOptimizer(PerceptionMeasures):
    """VTK filter: optimise opacity, lighting and colour of a spec; output the optimised image.

    Has every parameter of :class:`~dvr_perception.filters.PerceptionMeasures` (``spec_file``
    / ``spec_json``, ``camera_json``, ``view``, ``width``, ``height``, ``input_array``; ``sigma``
    is not used: the optimiser's curvature uses the default scale) plus the ones below, each
    also settable ParaView-style (``SetStages("opacity,lighting")``, ``SetWeights(1, 0, 1)``).

    Attributes
    ----------
    stages : tuple of str
        Stages in order (default ``("opacity", "lighting", "colour")``); a comma-separated
        string is accepted.
    weights : tuple of float
        ``(w_v, w_s, w_t)`` of Eq. 12 (default ``(1, 1, 1)``).
    seed : int
        Seed of the annealing moves (default 0).
    max_iter : int
        Iterations per stage (default 10).
    resolution : int
        Long side of the optimisation camera; 0 (default) uses the optimiser's default.
    region : tuple or None
        The lens: only rays in this rectangle or circle of the output image drive the
        objective (see :func:`as_region`); ``None`` (default) is the whole image.
    result : OptimizationResult or None
        The last optimisation's result (``None`` before the first successful update).
    """

    stages = Parameter(("opacity", "lighting", "colour"), as_stages)
    weights = Parameter((1.0, 1.0, 1.0), as_weights)
    seed = Parameter(0, as_seed)
    max_iter = Parameter(10, as_positive_int)
    resolution = Parameter(0, as_resolution)
    region = Parameter(None, as_region)

    def __init__(self) -> None:
        super().__init__()
        self.result = None
        self._spacing = (1.0, 1.0, 1.0)

    def _callback(self, total: int):
        def callback(info) -> None:
            self.UpdateProgress(0.2 + 0.7 * min(1.0, info.nit / total))
            if self.GetAbortExecute():
                raise StopIteration

        return callback

    def _optimize(self, volume, spec, camera, analyzer=None):
        from dvr_perception.optimize import optimize

        stages = self.stages
        return optimize(volume, spec, camera, stages=stages, weights=self.weights, seed=self.seed,
                        region=self.region, callback=self._callback(len(stages) * self.max_iter),
                        max_iter=self.max_iter, resolution=self.resolution or None,
                        analyzer=analyzer, progress=self.progress_range(0.0, 0.2))  # fmt: skip

    def execute(self, image, output) -> None:
        """Optimise, render and measure the optimised spec, and fill the output."""
        self.UpdateProgress(0.0)
        self.result = None
        volume = self.load_input(image)
        spec = self.load_spec_parameters()
        volume = attach_labels(volume, spec)  # the spec's label volume, e.g. a .seg.nrrd
        check_spec_for_volume(spec, volume)
        camera = self.make_camera(volume, spec)
        self._spacing = tuple(volume.spacing)
        res = self._optimize(volume, spec, camera)
        self.UpdateProgress(0.9)
        opt = res.spec
        # the optimiser's rendering of the view with the optimised spec, as 'dvr-perception
        # optimize' measures it: equal to a fresh analysis (the measures are the same with or
        # without its re-evaluation cache, DECISIONS D7)
        result = res.analyses[-1] if res.analyses else None
        if result is None:
            curvature, _ = curvature_volume(volume, opt, progress=self.progress_range(0.9, 0.93))
            result = analyze(volume, opt, camera, curvature=curvature,
                             progress=self.progress_range(0.93, 0.96))  # fmt: skip
        self._fill_result(output, result, res, camera)

    def execute_piece(self, image, output, comm, piece: int, whole) -> None:
        """Optimise over the MPI ranks, each holding its piece (collective).

        Every rank keeps its brick's cache entries
        (:class:`~dvr_perception.distributed.RankSession`); rank 0 runs the optimiser, whose
        every evaluation broadcasts the parameters and composites the ranks' re-evaluations in
        view order; the others serve until rank 0 stops them.  The optimised spec's image is
        the user view's re-evaluation.  Piece 0 holds the output, whose field data adds
        ``ranks`` (:meth:`~dvr_perception.distributed.RankSession.stop`'s records).
        """
        from dvr_perception.distributed import RankSession
        from dvr_perception.optimize._problem import Params

        self.UpdateProgress(0.0)
        self.result = None
        part, spec, camera = self.piece_inputs(image, comm, piece, whole)
        self._spacing = tuple(image.GetSpacing())
        session = RankSession(comm, part, spec, sigma=1.0)  # the optimiser's curvature scale
        if comm.rank != 0:
            session.serve()
            output.Initialize()
            return
        res = self._optimize(None, spec, camera, analyzer=session.analyze)
        self.UpdateProgress(0.9)
        p = Params.from_spec(res.spec)
        result = session.caches[0].reevaluate(
            opacities=np.clip(p.opacities, 0.0, 1.0), lighting=p.materials(),
            colours=np.clip(p.colours, 0.0, 1.0), light_direction=p.light,
        )  # fmt: skip
        try:  # measured while the ranks serve: E_t may re-composite through them (D7)
            self._fill_result(output, result, res, camera)
        finally:
            records = session.stop()
        output.GetFieldData().AddArray(string_array([json.dumps(r) for r in records], "ranks"))

    def _fill_result(self, output, result, res, camera) -> None:
        """Measure the optimised rendering ``result`` and fill the output (see the module)."""
        from dvr_perception.optimize.explain import explanation_line

        opt, weights = res.spec, self.weights
        vis, shp, trn = visibility(result, opt), shape(result, opt), transparency(result, opt)
        lum = engine_luminance(result.rgba, opt.background)
        self.UpdateProgress(0.97)

        w, h = camera.width, camera.height
        output.SetExtent(0, w - 1, 0, h - 1, 0, 0)
        output.SetSpacing(1.0, 1.0, 1.0)
        output.SetOrigin(0.0, 0.0, 0.0)
        pd = output.GetPointData()
        pd.SetScalars(point_array(_rows_up(result.rgba, "float32"), "rgba"))
        for name, values, dtype in (
            ("luminance", lum, "float32"),
            ("visibility_deviation", vis.deviation, "float32"),
            ("shape_deviation", shp.deviation, "float32"),
            ("transparency_deviation", trn.deviation, "float32"),
            ("layer_set", trn.layer_set, "uint32"),
            ("region_id", trn.region_id, "int32"),
        ):
            pd.AddArray(point_array(_rows_up(values, dtype), name))

        fd = output.GetFieldData()
        names = list(result.names)
        final = {"E_v": vis.E_v, "E_s": shp.E_s, "E_t": trn.E_t}
        for term in _TERMS:
            fd.AddArray(double_array([final[term]], term))
        total = sum(a * final[t] for a, t in zip(weights, _TERMS, strict=True))
        fd.AddArray(double_array([total], "E"))
        whole = res.initial.get("whole", res.initial)  # the image's terms, like E_* above
        for term in (*_TERMS, "E"):
            fd.AddArray(double_array([whole[term]], f"initial_{term}"))
        if self.region is not None:  # the lens's own terms, before and after
            for term in (*_TERMS, "E"):
                fd.AddArray(double_array([res.initial[term]], f"lens_initial_{term}"))
                fd.AddArray(double_array([res.final[term]], f"lens_{term}"))
            fd.AddArray(string_array([_region_text(self.region)], "lens_region"))
        fd.AddArray(string_array(names, "structure_names"))
        pv, pt = vis.per_structure, trn.per_structure
        for key, values in (
            ("visible_share", [pv[n]["visible_share"] for n in names]),
            ("target_share", [pv[n]["target_share"] for n in names]),
            ("assigned_share", [pv[n]["assigned_share"] for n in names]),
            ("perceived_transparency", [_nan(pt[n]["perceived_transparency"]) for n in names]),
            ("expected_opacity", [pt[n]["expected_opacity"] for n in names]),
        ):
            fd.AddArray(double_array(values, key))
        structures = {s.name: s for s in opt.structures}
        ordered = [structures[n] for n in names]
        fd.AddArray(double_array([s.render_opacity for s in ordered], "opacity"))
        fd.AddArray(point_array([list(s.colour) for s in ordered], "color"))
        for key in ("ambient", "diffuse", "specular", "specular_power"):
            fd.AddArray(double_array([getattr(s.lighting, key) for s in ordered], key))
        fd.AddArray(point_array([list(opt.rendering.light_direction)], "light_direction"))
        fd.AddArray(double_array([res.status], "status"))
        fd.AddArray(double_array([res.nit], "iterations"))
        fd.AddArray(string_array([res.message], "status_message"))
        why = [explanation_line(n, res.structures[n]) for n in names if n in res.structures]
        fd.AddArray(string_array(why, "why"))
        before = [res.structures.get(n, {}) for n in names]
        for key in ("opacity_before", "share_before"):
            fd.AddArray(double_array([_nan(b.get(key)) for b in before], key))
        unit = opt.rendering.opacity_unit_distance
        unit = float(min(self._spacing)) if unit is None else float(unit)
        fd.AddArray(double_array([unit], "opacity_unit_distance"))
        fd.AddArray(string_array([json.dumps(spec_to_dict(opt))], "optimized_spec_json"))
        self.result = res
