"""``PerceptionMeasures``: render a volume and measure how well the rendering shows its structures.

One 3-D ``vtkImageData`` in; one 2-D ``vtkImageData`` of ``width x height x 1`` points out
(spacing 1, origin 0).  The filter runs the library pipeline
:func:`~dvr_perception.rays.curvature.curvature_volume` ->
:func:`~dvr_perception.rays.engine.analyze` -> :func:`~dvr_perception.measures.visibility`,
:func:`~dvr_perception.measures.shape`, :func:`~dvr_perception.measures.transparency` with
their default options.

Point data (one tuple per pixel)
    ``rgba`` (float32, 4 components): the engine's premultiplied colour and accumulated
    opacity (the active scalars); ``luminance`` (float32): linear CIE Y of ``rgba`` composited
    over the spec background; ``visibility_deviation``, ``shape_deviation``,
    ``transparency_deviation`` (float32): the per-pixel deviations of the three measures;
    ``layer_set`` (uint32): bitmask of the visible layers (bit ``k`` = structure ``k``);
    ``region_id`` (int32): sub-region index of the transparency measure.

Row order
    The engine's images have row 0 at the **top** (as a PNG); VTK images have point row
    ``j = 0`` at the **bottom**.  Every point array is flipped vertically, so the output shows
    upright in ParaView: engine pixel ``[row, col]`` is output point ``(i=col, j=H-1-row)``,
    i.e. ``engine = vtk_to_numpy(a).reshape(H, W, -1)[::-1]``.

Field data
    ``E_v``, ``E_s``, ``E_t``: one-tuple double arrays with the three deviations;
    ``structure_names`` (vtkStringArray); and, ordered like ``structure_names``, double arrays
    ``visible_share``, ``target_share`` (D1) and ``assigned_share`` (thickness) (image-wide
    shares of the visibility measure),
    ``perceived_transparency`` (area-weighted perceived transmittance of the transparency
    measure; **NaN** where it could not be determined, e.g. a structure that is not visible)
    and ``expected_opacity`` (the opacity the transparency measure expects).

Several MPI ranks
    With ``distributed`` on, when the pipeline asks for piece ``r`` of ``N`` and there are
    ``N`` MPI ranks (ParaView's
    ``mpiexec -n N pvbatch`` / ``pvserver``), each rank asks its input for the extent of its
    piece (VTK's block split, :func:`piece_extent`) plus the ghost layers the normals and the
    curvature need, so no rank reads the whole volume; the ranks then compute the serial
    result together (a :class:`~dvr_perception.distributed.RankSession`, whose ranks keep
    their cache entries while rank 0 measures, so that the transparency measure re-composites
    the view without an enclosing layer as the serial filter does) and piece 0 holds the
    whole output image, the other pieces are empty.  Rank 0's field data adds the string
    array ``ranks``: one JSON record per rank (``rank``, ``extent``, ``voxels``, ``cells``,
    ``order``, ``views``, ``evaluations``, ``seconds``, ``peak_rss_mb``).

Errors are reported through VTK's error mechanism (see :mod:`dvr_perception.filters._base`).
"""

from __future__ import annotations

import json
import math

import numpy as np

from dvr_perception._vtk import vtkDataObject, vtkExtentTranslator, vtkStreamingDemandDrivenPipeline
from dvr_perception.errors import DVRInputError
from dvr_perception.filters._base import (
    DVRFilterBase,
    Parameter,
    as_flag,
    as_positive_float,
    as_positive_int,
    as_text,
    double_array,
    engine_luminance,
    point_array,
    string_array,
)
from dvr_perception.measures import all_measures
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import attach_labels, check_spec_for_volume, loads_json
from dvr_perception.volume.convert import has_identity_direction

__all__ = ["PerceptionMeasures", "piece_extent"]


def as_view(value, name: str):
    """Accept ``None``/``""`` (use the spec's view) or ``(azimuth, elevation[, zoom])``."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    try:
        vals = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        vals = ()
    if len(vals) == 2:
        vals = (*vals, 1.0)
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals) or vals[2] <= 0:
        raise DVRInputError(
            f"{name}: expected (azimuth, elevation[, zoom]) finite numbers with zoom > 0, "
            f"got {value!r}"
        )
    return vals


class PerceptionMeasures(DVRFilterBase):
    """VTK filter: DVR image and per-pixel / overall perceptual deviations of a volume.

    The parameters are attributes, each also settable ParaView-style (``SetCameraJson(text)``,
    ``SetView(30, 10, 1)``, ``SetWidth(256)``, ...); changing one marks the filter modified.

    Attributes
    ----------
    spec_file : str
        Path of a structure-spec JSON file, or
    spec_json : str
        the spec as JSON text (exactly one of the two).
    camera_json : str
        A camera as JSON text (:meth:`~dvr_perception.rays.camera.Camera.to_dict` format;
        missing ``width``/``height`` come from the attributes below).  When empty, the camera
        orbits the volume as given by ``view``.
    view : tuple of float or None
        ``(azimuth, elevation, zoom)`` (:meth:`~dvr_perception.rays.camera.Camera.from_view`);
        ``None`` (default) uses the spec's ``view`` or ``(0, 0, 1)``.
    width, height : int
        Image size in pixels (default 512 x 512) when ``camera_json`` does not give it.
    sigma : float
        Gaussian scale of the boundary curvature (default 1.0).
    input_array : str
        Point array to render (default "": the active scalars).
    distributed : bool
        With several MPI ranks, each rank reads and analyses its own piece (see *Several MPI
        ranks*; every rank must execute the filter together, as pvbatch's scripts do).  Off
        (default): every rank reads the whole volume and rank 0 computes.
    """

    camera_json = Parameter("", as_text)
    distributed = Parameter(False, as_flag)
    view = Parameter(None, as_view)
    width = Parameter(512, as_positive_int)
    height = Parameter(512, as_positive_int)
    sigma = Parameter(1.0, as_positive_float)

    def __init__(self) -> None:
        super().__init__("vtkImageData")

    # -- camera -----------------------------------------------------------------------------------
    def _camera_dict(self) -> dict | None:
        if not self.camera_json.strip():
            return None
        d = loads_json(self.camera_json, "camera_json")
        if not isinstance(d, dict):
            raise DVRInputError(f"camera_json: expected a JSON object, got {type(d).__name__}")
        d = dict(d)
        d.setdefault("width", self.width)
        d.setdefault("height", self.height)
        return d

    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of the output image for the current parameters."""
        d = self._camera_dict()
        if d is None:
            return self.width, self.height
        cam = Camera.from_dict(d, source="camera_json")
        return cam.width, cam.height

    def make_camera(self, volume, spec) -> Camera:
        """Return the camera for ``volume`` (``camera_json``, else the orbit ``view``)."""
        d = self._camera_dict()
        if d is not None:  # the view's camera, in world coordinates
            return Camera.from_dict(d, source="camera_json").in_volume_frame(volume)
        az, el, zoom = self.view or spec.view or (0.0, 0.0, 1.0)
        return Camera.from_view(
            volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=self.width, height=self.height
        )

    # -- pipeline ---------------------------------------------------------------------------------
    def information(self, in_info, out_info) -> None:
        """Declare the 2-D output extent ``(0, W-1, 0, H-1, 0, 0)``, spacing 1, origin 0."""
        w, h = self.image_size()
        info = out_info.GetInformationObject(0)
        key = vtkStreamingDemandDrivenPipeline
        info.Set(key.WHOLE_EXTENT(), (0, w - 1, 0, h - 1, 0, 0), 6)
        info.Set(vtkDataObject.SPACING(), 1.0, 1.0, 1.0)
        info.Set(vtkDataObject.ORIGIN(), 0.0, 0.0, 0.0)

    def execute(self, image, output) -> None:
        """Render, measure and fill the output image and its field data."""
        self.UpdateProgress(0.0)
        volume = self.load_input(image)
        spec = self.load_spec_parameters()
        volume = attach_labels(volume, spec)  # the spec's label volume, e.g. a .seg.nrrd
        check_spec_for_volume(spec, volume)
        camera = self.make_camera(volume, spec)
        self.UpdateProgress(0.05)
        curvature, _ = curvature_volume(volume, spec, sigma=self.sigma,
                                        progress=self.progress_range(0.05, 0.3))  # fmt: skip
        result = analyze(volume, spec, camera, curvature=curvature,
                         progress=self.progress_range(0.3, 0.7))  # fmt: skip
        self._fill(output, result, spec, camera)

    # -- several MPI ranks ------------------------------------------------------------------------
    def pieces(self, out_info, comm=None) -> tuple[int, int, object]:
        """Return ``(piece, pieces, communicator)``, or ``(0, 1, None)`` for one process.

        The ranks compute together when the pipeline asks for piece ``r`` of ``N`` and there
        are ``N`` MPI ranks.
        """
        info = out_info.GetInformationObject(0)
        key = vtkStreamingDemandDrivenPipeline
        if not self.distributed or info is None or not info.Has(key.UPDATE_NUMBER_OF_PIECES()):
            return 0, 1, None
        n = int(info.Get(key.UPDATE_NUMBER_OF_PIECES()))
        if n < 2:
            return 0, 1, None
        from dvr_perception.parallel import communicator

        comm = comm or communicator()
        if comm.size != n:
            return 0, 1, None
        return int(info.Get(key.UPDATE_PIECE_NUMBER())), n, comm

    def RequestUpdateExtent(self, request, in_info, out_info):
        """Pipeline pass: the whole input, or with several ranks this rank's piece + ghosts."""
        piece, n, _ = self.pieces(out_info)
        if n == 1:
            return super().RequestUpdateExtent(request, in_info, out_info)
        return self._guarded(self._request_piece, in_info, piece, n)

    def _request_piece(self, in_info, piece: int, n: int) -> None:
        from dvr_perception.rays.ranks import ghost_levels

        info = in_info[0].GetInformationObject(0)
        key = vtkStreamingDemandDrivenPipeline
        whole = info.Get(key.WHOLE_EXTENT())
        spacing = info.Get(vtkDataObject.SPACING()) if info.Has(vtkDataObject.SPACING()) else None
        ghost = ghost_levels(spacing or (1.0, 1.0, 1.0), self.sigma)
        # the extent as ONE piece: asked for piece r of N, ParaView's NRRD reader
        # (vtkPNrrdReader) splits the requested extent once more
        info.Set(key.UPDATE_EXTENT(), piece_extent(whole, piece, n, ghost), 6)
        info.Set(key.UPDATE_PIECE_NUMBER(), 0)
        info.Set(key.UPDATE_NUMBER_OF_PIECES(), 1)
        info.Set(key.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)

    def RequestData(self, request, in_info, out_info):
        """Pipeline pass: :meth:`execute`, or with several ranks :meth:`execute_piece`."""
        piece, n, comm = self.pieces(out_info)
        if n == 1:
            return super().RequestData(request, in_info, out_info)
        self.warning_messages = []
        key = vtkDataObject.DATA_OBJECT()
        output = out_info.GetInformationObject(0).Get(key)
        image = in_info[0].GetInformationObject(0).Get(key)
        whole = (
            in_info[0].GetInformationObject(0).Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT())
        )
        status = self._guarded(self._collective, comm, image, output, piece, whole)
        if not status and output is not None:
            output.Initialize()
        return status

    def _collective(self, comm, image, output, piece: int, whole) -> None:
        """:meth:`execute_piece`; an error on any rank ends the MPI job (one line, exit 2/1).

        The other ranks would otherwise wait forever for the failed rank's messages
        (:func:`~dvr_perception.parallel.abort_on_error`).
        """
        from dvr_perception.parallel import abort_on_error

        with abort_on_error(comm, self.label):
            self.execute_piece(image, output, comm, piece, whole)

    def piece_inputs(self, image, comm, piece: int, whole) -> tuple:
        """Return this rank's ``(Piece, spec, camera)`` for the input piece ``image``."""
        from dvr_perception.rays import bricks
        from dvr_perception.rays.ranks import Piece

        if comm.rank != piece:
            raise DVRInputError(f"{self.label}: rank {comm.rank} was asked for piece {piece}")
        if not has_identity_direction(image):  # pieces are placed by their index extents
            raise DVRInputError(
                f"{self.label}: an input image with a direction matrix cannot be split across "
                "MPI ranks; run on one rank (or resample the image to the identity direction)"
            )
        volume = self.load_input(image)
        spec = self.load_spec_parameters()
        ext = image.GetExtent()
        offset = tuple(int(ext[2 * a] - whole[2 * a]) for a in (2, 1, 0))
        shape = tuple(int(whole[2 * a + 1] - whole[2 * a] + 1) for a in (2, 1, 0))
        origin = tuple(
            o + w * sp
            for o, w, sp in zip(image.GetOrigin(), whole[::2], volume.spacing, strict=True)
        )
        geometry = bricks.Geometry(shape, volume.spacing, origin, volume.data.dtype)
        owned = piece_extent(whole, piece, comm.size, 0)
        brick = bricks.from_piece_extent(owned, whole)
        camera = self.make_camera(geometry, spec)
        return Piece(volume, offset, brick, geometry), spec, camera

    def execute_piece(self, image, output, comm, piece: int, whole) -> None:
        """Compute this rank's part of the output (collective; see *Several MPI ranks*)."""
        from dvr_perception.distributed import RankSession

        part, spec, camera = self.piece_inputs(image, comm, piece, whole)
        # a session (not a one-off walk): the ranks keep their cache entries while rank 0
        # measures, so the transparency measure can re-composite the view without an
        # enclosing layer (decision D7), as the serial filter does by walking again
        session = RankSession(comm, part, spec, sigma=self.sigma)
        if comm.rank != 0:
            session.serve()
            output.Initialize()
            return
        try:
            result = session.analyze(camera)
            self._fill(output, result, spec, camera)
        finally:
            records = session.stop()
        output.GetFieldData().AddArray(string_array([json.dumps(r) for r in records], "ranks"))

    def _fill(self, output, result, spec, camera) -> None:
        """Measure ``result`` and fill the output image and its field data."""
        vis, shp, trn = all_measures(result, spec)
        self.UpdateProgress(0.95)
        lum = engine_luminance(result.rgba, spec.background)

        w, h = camera.width, camera.height
        output.SetExtent(0, w - 1, 0, h - 1, 0, 0)
        output.SetSpacing(1.0, 1.0, 1.0)
        output.SetOrigin(0.0, 0.0, 0.0)
        pd = output.GetPointData()
        rgba = point_array(_rows_up(result.rgba, np.float32), "rgba")
        pd.SetScalars(rgba)
        for name, values, dtype in (
            ("luminance", lum, np.float32),
            ("visibility_deviation", vis.deviation, np.float32),
            ("shape_deviation", shp.deviation, np.float32),
            ("transparency_deviation", trn.deviation, np.float32),
            ("layer_set", trn.layer_set, np.uint32),
            ("region_id", trn.region_id, np.int32),
        ):
            pd.AddArray(point_array(_rows_up(values, dtype), name))

        fd = output.GetFieldData()
        names = list(result.names)
        fd.AddArray(double_array([vis.E_v], "E_v"))
        fd.AddArray(double_array([shp.E_s], "E_s"))
        fd.AddArray(double_array([trn.E_t], "E_t"))
        fd.AddArray(string_array(names, "structure_names"))
        per_v = vis.per_structure
        per_t = trn.per_structure
        fd.AddArray(double_array([per_v[n]["visible_share"] for n in names], "visible_share"))
        fd.AddArray(double_array([per_v[n]["target_share"] for n in names], "target_share"))
        fd.AddArray(double_array([per_v[n]["assigned_share"] for n in names], "assigned_share"))
        fd.AddArray(
            double_array(
                [_nan(per_t[n]["perceived_transparency"]) for n in names],
                "perceived_transparency",
            )
        )
        fd.AddArray(double_array([per_t[n]["expected_opacity"] for n in names], "expected_opacity"))


def piece_extent(whole, piece: int, pieces: int, ghost: int = 0) -> tuple[int, ...]:
    """Return VTK's extent of piece ``piece`` of ``pieces`` of the extent ``whole``.

    ``ghost`` layers are added (clamped to ``whole``); ``vtkExtentTranslator``'s block split,
    as VTK's pipeline splits image data.

    Examples
    --------
    >>> piece_extent((0, 63, 0, 63, 0, 63), 1, 2), piece_extent((0, 63, 0, 63, 0, 63), 1, 2, 4)
    ((0, 63, 0, 63, 31, 63), (0, 63, 0, 63, 27, 63))
    """
    t = vtkExtentTranslator()
    t.SetWholeExtent(*[int(v) for v in whole])
    t.SetPiece(int(piece))
    t.SetNumberOfPieces(int(pieces))
    t.SetGhostLevel(int(ghost))
    t.SetSplitModeToBlock()
    t.PieceToExtent()
    return tuple(int(v) for v in t.GetExtent())


def _rows_up(values, dtype) -> np.ndarray:
    """Reorder a top-row-first ``(H, W[, C])`` array to VTK point order (bottom row first)."""
    a = np.asarray(values, dtype=dtype)[::-1]
    h, w = a.shape[:2]
    return np.ascontiguousarray(a.reshape(h * w, *a.shape[2:]))


def _nan(value) -> float:
    return math.nan if value is None else float(value)
