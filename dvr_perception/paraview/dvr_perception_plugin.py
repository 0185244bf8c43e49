"""ParaView plugin: the dvr_perception filters under the menu "Filters > DVR Perception".

Load it with *Tools > Manage Plugins > Load New...*, ``LoadPlugin(path, ns=globals())`` in
pvpython, or put this folder on ``PV_PLUGIN_PATH``.  ParaView 5.11 with Python >= 3.11 also
needs ``dvr_perception/paraview/pvsite`` on ``PYTHONPATH`` (see ``docs/guide/paraview.md``).

The three proxies are shells: they declare the properties ParaView shows and hand every pipeline
pass to the library's VTK filter (:mod:`dvr_perception.filters`), which is imported only when
the filter first executes.  Parameter values are validated by the library when the filter
runs, so a bad value (e.g. a negative sigma typed in Python) becomes an error message in
*Output Messages*, never an exception inside ParaView.  With several MPI ranks, the filters
read the whole volume on every rank and compute on piece 0 (rank 0); *Perception Measures*
and *Optimize Transfer Function* with *Distributed* on (what ``dvr-perception pvbatch --ranks
N`` sets) read one piece (plus ghost layers) per rank and the ranks compute the serial result
together (``dvr_perception.distributed``; every rank must execute the filter together, so it is
off by default in the GUI).  Either way piece 0 holds the whole output and the other pieces
are empty.
"""

import os
import sys

from paraview.util.vtkAlgorithm import VTKPythonAlgorithmBase, smdomain, smhint, smproperty, smproxy

paraview_plugin_name = "DVRPerception"
paraview_plugin_version = "0.1.0"

_CATEGORY = '<ShowInMenu category="DVR Perception" />'
_IMAGE_INPUT = '<InputArrayDomain name="input_array" attribute_type="point" />'
_ARRAY_LIST = (
    '<ArrayListDomain name="array_list" attribute_type="Scalars" input_domain_name="input_array">'
    '<RequiredProperties><Property name="Input" function="Input" /></RequiredProperties>'
    "</ArrayListDomain>"
)
_MULTI_LINE = '<Widget type="multi_line" />'
#: On *Apply* the GUI shows the 2-D output in a view of its own (split beside the active one),
#: never as a slab in the 3-D view: ParaView's preferred-view hint.
_OWN_VIEW = '<View type="SpreadSheetView" />'
#: The documented range of each numeric property: ``(min, max, integer)``.  The ``smdomain``
#: decorators below show them in the GUI; :meth:`_LibraryShell._set_in_range` holds values set
#: from Python to them too.
RANGES = {
    "Sigma": (0.1, 10.0, False),
    "Azimuth": (-180.0, 180.0, False),
    "Elevation": (-90.0, 90.0, False),
    "Zoom": (0.1, 10.0, False),
    "Width": (16, 4096, True),
    "Height": (16, 4096, True),
    "UseSpecView": (0, 1, True),
    "FollowView": (0, 1, True),
    "Distributed": (0, 1, True),
    "Weights": (0.0, 100.0, False),
    "Seed": (0, 1000000, True),
    "MaxIterations": (1, 1000, True),
    "Resolution": (0, 1024, True),
}


def _setup_paths():
    """Make ``dvr_perception`` and its dependencies importable; apply the compat shims."""
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)
    import dvr_boot

    dvr_boot.bind()  # the package holding this folder, its site-packages kept off the path
    from dvr_perception import _paraview_compat

    _paraview_compat.setup()


_setup_paths()
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the plugin's own modules
from dvr_volume_reader import VolumeReader  # noqa: E402, F401  (reader "DVR Perception volume")


def run_macro(action):
    """Run one DVR Perception toolbar action (``paraview/macros/DVR_*.py`` call this).

    ``action`` is ``"measure"``, ``"optimise"``, ``"refine"`` or ``"undo"``; see
    ``paraview/dvr_view.py``, imported from this plugin's folder.
    """
    here = os.path.dirname(os.path.abspath(__file__))
    if here not in sys.path:
        sys.path.insert(0, here)
    import dvr_view

    return dvr_view.run_macro(action)


class _LibraryShell(VTKPythonAlgorithmBase):
    """Forwards the pipeline passes to a lazily created ``dvr_perception.filters`` filter."""

    _filter_name = ""
    _label = ""

    def __init__(self):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=1, inputType="vtkImageData", nOutputPorts=1, outputType="vtkImageData"
        )
        self._values = {}
        self._invalid = {}
        self._impl = None
        self._last_error = None

    def _set(self, name, value):
        self._invalid.pop(name, None)
        if self._values.get(name, object()) != value:
            self._values[name] = value
            self.Modified()

    def _set_in_range(self, name, value, prop):
        """Set ``name`` if ``value`` lies in the property's documented range (:data:`RANGES`).

        A value outside it (typed in Python: the GUI's widgets keep to the range) is not
        taken: the filter fails with one error naming the property until it is set right.
        """
        from dvr_perception.errors import DVRInputError
        from dvr_perception.filters._base import check_range

        low, high, integer = RANGES[prop]
        try:
            checked = (
                [check_range(v, prop, low, high, integer=integer) for v in value]
                if (isinstance(value, tuple))
                else check_range(value, prop, low, high, integer=integer)
            )
        except DVRInputError as exc:
            self._invalid[name] = f"{self._label}: {exc}"
            self.Modified()
            return
        self._set(name, tuple(checked) if isinstance(value, tuple) else checked)

    def _library_filter(self):
        """Create the library filter (first call only) and push the current values into it."""
        if self._impl is None:
            from dvr_perception import filters

            self._impl = getattr(filters, self._filter_name)()
            self._impl.AddObserver("ProgressEvent", self._forward_progress)
        impl = self._impl
        from dvr_perception.errors import DVRInputError

        try:
            for message in self._invalid.values():
                raise DVRInputError(message)
            for name, value in self._parameters().items():
                setattr(impl, name, value)
        except DVRInputError as exc:
            # one message per property change, not one per pipeline pass
            key = (self.GetMTime(), str(exc))
            if key != self._last_error:
                self._last_error = key
                impl.report_error(str(exc))
            return None
        return impl

    def _forward_progress(self, obj, event):
        self.UpdateProgress(obj.GetProgress())

    def _parameters(self):
        """The library attribute values for the current property values."""
        raise NotImplementedError

    def RequestInformation(self, request, in_info, out_info):
        impl = self._library_filter()
        return 0 if impl is None else impl.RequestInformation(request, in_info, out_info)

    @staticmethod
    def _ranks_together(impl, out_info):
        """Whether the library filter computes with every rank on its piece (MPI)."""
        return hasattr(impl, "pieces") and impl.pieces(out_info)[1] > 1

    def RequestUpdateExtent(self, request, in_info, out_info):
        impl = self._library_filter()
        if impl is not None and self._ranks_together(impl, out_info):
            return impl.RequestUpdateExtent(request, in_info, out_info)  # piece + ghost layers
        if impl is None or not impl.RequestUpdateExtent(request, in_info, out_info):
            return 0
        # The whole volume, unsplit, on every rank: the library asks for the whole extent, but
        # a parallel reader (vtkPNrrdReader) turns "piece r of N" back into a slab unless the
        # request is one piece.  Every rank asks the same, so a reader that reads collectively
        # (MPI-IO) re-executes on all ranks together; only piece 0 computes (RequestData).
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        info = in_info[0].GetInformationObject(0)
        info.Set(sddp.UPDATE_PIECE_NUMBER(), 0)
        info.Set(sddp.UPDATE_NUMBER_OF_PIECES(), 1)
        info.Set(sddp.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)
        return 1

    def RequestData(self, request, in_info, out_info):
        self._executing = True  # FollowView's pvserver message: when it runs, not on Apply
        try:
            return self._request_data(request, in_info, out_info)
        finally:
            self._executing = False

    def _request_data(self, request, in_info, out_info):
        impl = self._library_filter()
        if impl is not None and self._ranks_together(impl, out_info):
            return impl.RequestData(request, in_info, out_info)  # every rank, collectively
        if _requested_piece(out_info) > 0:
            # several MPI ranks: piece 0 (rank 0) computes everything, the others stay empty
            from vtkmodules.vtkCommonDataModel import vtkDataObject

            out_info.GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT()).Initialize()
            return 1
        impl = self._library_filter()
        return 0 if impl is None else impl.RequestData(request, in_info, out_info)


def _view_camera(algorithm):
    """``CameraJSON`` of the render view showing ``algorithm``'s input, or None.

    Only where the filter runs in the client's own process (the GUI, pvpython without
    ``Connect``; one MPI rank): the filter's proxy (the one whose VTK object is ``algorithm``)
    and its input are found among the session's sources, and the render views that show the
    input; the active view if it is one of them, else the first.  Only properties are read
    (``FindRepresentation`` never creates a representation), so no pipeline runs from here.
    Under pvserver the server has no session of its own: None, and one line says so.
    """
    from paraview import servermanager
    from paraview.modules.vtkRemotingCore import vtkProcessModule

    pm = vtkProcessModule.GetProcessModule()
    conn = servermanager.ActiveConnection
    if conn is None or conn.IsRemote() or pm.GetNumberOfLocalPartitions() > 1:
        server = (vtkProcessModule.PROCESS_SERVER, vtkProcessModule.PROCESS_DATA_SERVER)
        executing = getattr(algorithm, "_executing", False)
        if vtkProcessModule.GetProcessType() in server and executing and not algorithm._told:
            algorithm._told = True
            print(
                f"DVR Perception: {algorithm._label} on pvserver takes the spec's view "
                "(FollowView needs the client's view: use the toolbar's actions)",
                flush=True,
            )
        return None
    import json

    from paraview import simple
    from view_camera import camera_from_view

    own = [p for p in simple.GetSources().values() if p.GetClientSideObject() is algorithm]
    source = own[0].Input if own else None
    if source is None:
        return None
    views = []
    for view in simple.GetViews():
        if view.GetXMLName() != "RenderView":
            continue
        rep = servermanager.GetRepresentation(source, view)
        if rep is not None and rep.Visibility:
            views.append(view)
    if not views:
        return None
    active = simple.GetActiveView()
    return json.dumps(camera_from_view(active if active in views else views[0]))


def _requested_piece(out_info):
    """The piece of the output the pipeline asks for (ParaView: the MPI rank; 0 when serial)."""
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

    info = out_info.GetInformationObject(0)
    key = sddp.UPDATE_PIECE_NUMBER()
    return info.Get(key) if info is not None and info.Has(key) else 0


# -- properties shared by both filters (a decorated method may be bound in several classes)
@smproperty.stringvector(name="ScalarArray", default_values="")
@smdomain.xml(_ARRAY_LIST)
def SetScalarArray(self, value):
    self._set("input_array", value)


@smproperty.stringvector(name="SpecFile", default_values="")
@smdomain.filelist()
@smhint.filechooser(extensions="json", file_description="Structure spec (JSON)")
def SetSpecFile(self, value):
    self._set("spec_file", value)


@smproperty.stringvector(name="SpecJSON", default_values="")
@smhint.xml(_MULTI_LINE)
def SetSpecJSON(self, value):
    self._set("spec_json", value)


@smproperty.doublevector(name="Sigma", default_values=1.0)
@smdomain.doublerange(min=RANGES["Sigma"][0], max=RANGES["Sigma"][1])
def SetSigma(self, value):
    self._set_in_range("sigma", value, "Sigma")


@smproxy.filter(name="DVRStructuralLayers", label="Structural Layers", support_reload=False)
@smhint.xml(_CATEGORY)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@smdomain.xml(_IMAGE_INPUT)
class StructuralLayers(_LibraryShell):
    """Adds ``structure_id``, ``boundary`` and ``curvature`` point arrays to a volume."""

    _filter_name = "StructuralLayers"
    _label = "Structural Layers"

    def __init__(self):
        _LibraryShell.__init__(self)
        self._values = {"input_array": "", "spec_file": "", "spec_json": "", "sigma": 1.0}

    def _parameters(self):
        return dict(self._values)

    # the properties both filters share (the module-level functions above)
    SetScalarArray = SetScalarArray
    SetSpecFile = SetSpecFile
    SetSpecJSON = SetSpecJSON
    SetSigma = SetSigma


@smproxy.filter(name="DVRPerceptionMeasures", label="Perception Measures", support_reload=False)
@smhint.xml(_CATEGORY)
@smhint.xml(_OWN_VIEW)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@smdomain.xml(_IMAGE_INPUT)
class PerceptionMeasures(_LibraryShell):
    """Renders the volume; outputs the image, per-pixel deviations and E_v, E_s, E_t."""

    _filter_name = "PerceptionMeasures"
    _label = "Perception Measures"

    def __init__(self):
        _LibraryShell.__init__(self)
        self._values = {
            "input_array": "",
            "spec_file": "",
            "spec_json": "",
            "sigma": 1.0,
            "camera_json": "",
            "use_spec_view": 1,
            "azimuth": 0.0,
            "elevation": 0.0,
            "zoom": 1.0,
            "width": 512,
            "height": 512,
            "distributed": 0,
            "follow_view": 1,
        }
        self._followed = None
        self._told = False

    def _parameters(self):
        v = dict(self._values)
        v["distributed"] = bool(v["distributed"])
        view = (v.pop("azimuth"), v.pop("elevation"), v.pop("zoom"))
        given = (v["camera_json"] or "").strip()
        follow = v.pop("follow_view") and v["use_spec_view"] and not given
        v["view"] = None if v.pop("use_spec_view") else view
        self._followed = _view_camera(self) if follow else None
        if self._followed:
            v["camera_json"] = self._followed
        return v

    # the properties both filters share (the module-level functions above)
    SetScalarArray = SetScalarArray
    SetSpecFile = SetSpecFile
    SetSpecJSON = SetSpecJSON
    SetSigma = SetSigma

    @smproperty.stringvector(name="CameraJSON", default_values="", panel_visibility="advanced")
    @smhint.xml(_MULTI_LINE)
    def SetCameraJSON(self, value):
        self._set("camera_json", value)

    @smproperty.intvector(name="Distributed", default_values=0, panel_visibility="advanced")
    @smdomain.xml('<BooleanDomain name="bool" />')
    def SetDistributed(self, value):
        """Each MPI rank reads and analyses its own piece (all ranks execute together)."""
        self._set_in_range("distributed", value, "Distributed")

    @smproperty.intvector(name="UseSpecView", default_values=1)
    @smdomain.xml('<BooleanDomain name="bool" />')
    def SetUseSpecView(self, value):
        self._set_in_range("use_spec_view", value, "UseSpecView")

    @smproperty.intvector(name="FollowView", default_values=1, panel_visibility="advanced")
    @smdomain.xml(
        '<BooleanDomain name="bool" /><Documentation>With no CameraJSON and UseSpecView on: '
        "the camera of the render view that shows the input (the active one if several), "
        "read whenever the filter executes, in the GUI and in pvpython without Connect; "
        "under pvserver the spec's view (the toolbar's actions pass the client's view)."
        "</Documentation>"
    )
    def SetFollowView(self, value):
        self._set_in_range("follow_view", value, "FollowView")

    @smproperty.doublevector(name="Azimuth", default_values=0.0)
    @smdomain.doublerange(min=RANGES["Azimuth"][0], max=RANGES["Azimuth"][1])
    def SetAzimuth(self, value):
        self._set_in_range("azimuth", value, "Azimuth")

    @smproperty.doublevector(name="Elevation", default_values=0.0)
    @smdomain.doublerange(min=RANGES["Elevation"][0], max=RANGES["Elevation"][1])
    def SetElevation(self, value):
        self._set_in_range("elevation", value, "Elevation")

    @smproperty.doublevector(name="Zoom", default_values=1.0)
    @smdomain.doublerange(min=RANGES["Zoom"][0], max=RANGES["Zoom"][1])
    def SetZoom(self, value):
        self._set_in_range("zoom", value, "Zoom")

    @smproperty.intvector(name="Width", default_values=512)
    @smdomain.intrange(min=RANGES["Width"][0], max=RANGES["Width"][1])
    def SetWidth(self, value):
        self._set_in_range("width", value, "Width")

    @smproperty.intvector(name="Height", default_values=512)
    @smdomain.intrange(min=RANGES["Height"][0], max=RANGES["Height"][1])
    def SetHeight(self, value):
        self._set_in_range("height", value, "Height")


@smproxy.filter(
    name="DVROptimizeTransferFunction", label="Optimize Transfer Function", support_reload=False
)
@smhint.xml(_CATEGORY)
@smhint.xml(_OWN_VIEW)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@smdomain.xml(_IMAGE_INPUT)
class OptimizeTransferFunction(_LibraryShell):
    """Optimises opacity, lighting and colour; outputs the optimised image and parameters.

    A shell over ``dvr_perception.filters.TransferFunctionOptimizer``: the output has the point
    and field data of *Perception Measures* for the optimised spec, plus the optimised
    per-structure ``opacity``, ``color``, ``ambient``, ``diffuse``, ``specular``,
    ``specular_power``, ``initial_E*`` and the string ``optimized_spec_json`` (apply it to a
    volume display with ``paraview/dvr_view.py``'s ``optimise_this_view``, the *DVR Optimise
    View* macro, or ``paraview/apply_result.py``).

    The last output is kept: setting only ``ParaViewSSIM`` (what ``optimise_this_view``
    reports after rendering the applied result in ParaView) re-executes without optimising
    again and adds the field array ``paraview_ssim`` to the same output.
    """

    _filter_name = "TransferFunctionOptimizer"
    _label = "Optimize Transfer Function"

    def __init__(self):
        _LibraryShell.__init__(self)
        self._values = {
            "input_array": "",
            "spec_file": "",
            "spec_json": "",
            "camera_json": "",
            "use_spec_view": 1,
            "azimuth": 0.0,
            "elevation": 0.0,
            "zoom": 1.0,
            "width": 256,
            "height": 256,
            "stages": "opacity,lighting,colour",
            "weights": (1.0, 1.0, 1.0),
            "seed": 0,
            "max_iter": 10,
            "resolution": 0,
            "distributed": 0,
            "follow_view": 1,
        }
        self._followed = None
        self._told = False
        self._ssim = -1.0
        self._cache = None
        self._cache_key = None

    _parameters = PerceptionMeasures._parameters
    SetDistributed = PerceptionMeasures.SetDistributed

    # the spec and view properties of the other filters (Sigma is not used by the optimiser)
    SetScalarArray = SetScalarArray
    SetSpecFile = SetSpecFile
    SetSpecJSON = SetSpecJSON
    SetCameraJSON = PerceptionMeasures.SetCameraJSON
    SetUseSpecView = PerceptionMeasures.SetUseSpecView
    SetFollowView = PerceptionMeasures.SetFollowView
    SetAzimuth = PerceptionMeasures.SetAzimuth
    SetElevation = PerceptionMeasures.SetElevation
    SetZoom = PerceptionMeasures.SetZoom

    @smproperty.intvector(name="Width", default_values=256)
    @smdomain.intrange(min=RANGES["Width"][0], max=RANGES["Width"][1])
    def SetWidth(self, value):
        self._set_in_range("width", value, "Width")

    @smproperty.intvector(name="Height", default_values=256)
    @smdomain.intrange(min=RANGES["Height"][0], max=RANGES["Height"][1])
    def SetHeight(self, value):
        self._set_in_range("height", value, "Height")

    @smproperty.stringvector(name="Stages", default_values="opacity,lighting,colour")
    def SetStages(self, value):
        self._set("stages", value)

    @smproperty.doublevector(name="Weights", default_values=[1.0, 1.0, 1.0])
    @smdomain.doublerange(min=RANGES["Weights"][0], max=RANGES["Weights"][1])
    def SetWeights(self, w_v, w_s, w_t):
        self._set_in_range("weights", (w_v, w_s, w_t), "Weights")

    @smproperty.intvector(name="Seed", default_values=0)
    @smdomain.intrange(min=RANGES["Seed"][0], max=RANGES["Seed"][1])
    def SetSeed(self, value):
        self._set_in_range("seed", value, "Seed")

    @smproperty.intvector(name="MaxIterations", default_values=10)
    @smdomain.intrange(min=RANGES["MaxIterations"][0], max=RANGES["MaxIterations"][1])
    def SetMaxIterations(self, value):
        self._set_in_range("max_iter", value, "MaxIterations")

    @smproperty.intvector(name="Resolution", default_values=0)
    @smdomain.intrange(min=RANGES["Resolution"][0], max=RANGES["Resolution"][1])
    def SetResolution(self, value):
        self._set_in_range("resolution", value, "Resolution")

    @smproperty.stringvector(name="Region", default_values="")
    @smdomain.xml(
        "<Documentation>The lens: only rays inside this part of the output image drive the "
        "optimisation. Empty = whole image; 'rect,x0,y0,x1,y1' or 'circle,cx,cy,r' in output "
        "pixels (x right, y down from the top-left corner).</Documentation>"
    )
    def SetRegion(self, value):
        self._set("region", value)

    @smproperty.doublevector(name="ParaViewSSIM", default_values=-1.0, panel_visibility="never")
    def SetParaViewSSIM(self, value):
        """SSIM of ParaView's rendering of the applied result vs the engine's (-1: none)."""
        value = float(value)
        if value != self._ssim:
            self._ssim = value
            self.Modified()

    def _request_data(self, request, in_info, out_info):
        impl = self._library_filter()
        if impl is None or self._ranks_together(impl, out_info) or _requested_piece(out_info) > 0:
            return _LibraryShell._request_data(self, request, in_info, out_info)
        from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkImageData

        source = in_info[0].GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT())
        output = out_info.GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT())
        key = (
            repr(sorted(self._values.items())),
            self._followed,
            source.GetMTime() if source else 0,
        )
        if self._cache is not None and key == self._cache_key:
            output.ShallowCopy(self._cache)  # only ParaViewSSIM changed: no new optimisation
        else:
            self._cache = self._cache_key = None
            if not _LibraryShell._request_data(self, request, in_info, out_info):
                return 0
            if output.GetFieldData().GetAbstractArray("optimized_spec_json") is None:
                return 1  # failed: the library reported the error; nothing to keep
            self._cache = vtkImageData()
            self._cache.ShallowCopy(output)
            self._cache_key = key
        if self._ssim >= 0:
            from dvr_perception.filters._base import double_array

            output.GetFieldData().AddArray(double_array([self._ssim], "paraview_ssim"))
        return 1
