"""pvbatch script: Perception Measures of one volume, with a ParaView rendering of it.

Usage (``dvr-perception pvbatch`` runs this with the right environment and Xvfb)::

    pvbatch dvr_perception/paraview/batch_measure.py VOLUME
        [--structures SPEC | --preset NAME | --classes N] [--view A,E[,Z] | --camera CAM]
        [--size N|WxH] [--shade|--no-shade] [--sigma S] --out DIR

VOLUME, the spec and the camera are resolved exactly as the ``dvr-perception`` commands do
(``dvr_perception.inputs.load_inputs``: the preset of ``state_files/`` whose recorded data
checksum matches the volume's, else a proposal; the spec's view, 512 x 512).  The volume goes
into ParaView through a ``TrivialProducer``; the *Perception Measures* filter of
``dvr_perception_plugin.py`` runs on it through ``paraview.simple``.  Written into DIR:

``screenshot.png``
    ParaView's own volume rendering (CPU ray caster) with the spec's colour and opacity
    transfer functions, material and background, seen by the same camera.
``image.png``, ``visibility_deviation.png``, ``shape_deviation.png``, ``transparency_deviation.png``
    The filter's output: the engine's image over the background and the three per-pixel
    deviation maps (Viridis; black where the ray met nothing).
``result.json``
    ``E_v``, ``E_s``, ``E_t``, per-structure shares, the camera and the files written.

Under ``mpiexec -n N pvbatch ... --ranks N`` (what ``dvr-perception pvbatch --ranks N`` runs)
the volume is opened with ParaView's reader instead, so each rank reads only its piece, the
camera comes from the reader's header information (the volume is never loaded whole; a spec is
required: ``--structures`` or ``--preset NAME``), and ``result.json`` adds
``ranks``: one record per rank (``rank``, ``extent``, ``voxels``, ``peak_rss_mb``, ...).

Errors print one line ``dvr-perception: error: ...`` on stderr and exit with status 2.
"""

import json
import os
import sys
import time

PROG = "dvr-perception"
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))  # the folder holding the dvr_perception package
PLUGIN = os.path.join(HERE, "dvr_perception_plugin.py")
# (output file, point array, colour range or None for "0..max")
DEVIATION_IMAGES = (
    ("visibility_deviation.png", "visibility_deviation", (0.0, 2.0)),
    ("shape_deviation.png", "shape_deviation", (0.0, 1.0)),
    ("transparency_deviation.png", "transparency_deviation", None),
)
PER_STRUCTURE = (
    "visible_share",
    "target_share",
    "assigned_share",
    "perceived_transparency",
    "expected_opacity",
)


class BatchError(Exception):
    """A problem with the input, reported as one line."""


def parse_args(argv):
    if HERE not in sys.path:
        sys.path.insert(0, HERE)
    import dvr_boot

    dvr_boot.bind()
    from dvr_perception._paraview_compat import setup

    try:
        setup()
    except RuntimeError as exc:
        raise BatchError(str(exc)) from None
    from dvr_perception.inputs import OptionParser, add_input_args

    parser = OptionParser(prog=f"{PROG} pvbatch", description=__doc__.split("\n")[0])
    add_input_args(parser)
    parser.add_argument("--sigma", type=float, default=1.0, help="curvature scale (default 1)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument(
        "--ranks", type=int, default=1, help="MPI ranks pvbatch runs on (mpiexec -n N)"
    )
    parser.add_argument("--no-screenshot", action="store_true", help="skip ParaView's rendering")
    return parser.parse_args(argv)


def transfer_function_points(spec, scalar_range=None):
    """ParaView's ``RGBPoints`` and ``Points`` lists for the spec's VTK transfer functions.

    The nodes are kept one GPU table entry apart over ``scalar_range`` (the data range) and
    the nodes' span (``GPU_TABLE_SAMPLES``): ParaView's GPU ray caster then gets a lookup
    texture OpenGL supports, without VTK's "incorrect lookup table mapping" warning.
    """
    from dvr_perception.export.vtk import GPU_TABLE_SAMPLES, to_vtk_transfer_functions

    ctf, otf = to_vtk_transfer_functions(spec, samples=GPU_TABLE_SAMPLES, scalar_range=scalar_range)
    rgb, node = [], [0.0] * 6
    for i in range(ctf.GetSize()):
        ctf.GetNodeValue(i, node)
        rgb += node[:4]
    pts, node = [], [0.0] * 4
    for i in range(otf.GetSize()):
        otf.GetNodeValue(i, node)
        pts += node
    return rgb, pts


def set_camera(view, camera):
    view.ViewSize = [camera.width, camera.height]
    view.CameraPosition = list(camera.position)
    view.CameraFocalPoint = list(camera.focal_point)
    view.CameraViewUp = list(camera.view_up)
    view.CameraViewAngle = camera.view_angle
    view.CameraParallelProjection = int(camera.parallel_projection)
    view.CameraParallelScale = camera.parallel_scale


def show_volume(pvs, source, array, inputs):
    """A render view with ``source`` as a ray-cast volume coloured by ``array``, seen by the
    inputs' camera, with the spec's background, opacity unit distance and shading; returns
    ``(view, display)`` (the transfer functions and the material are still ParaView's)."""
    spec, camera = inputs.spec, inputs.camera
    view = pvs.CreateView("RenderView")
    view.OrientationAxesVisibility = 0
    view.UseColorPaletteForBackground = 0
    view.Background = [float(c) for c in spec.background]
    display = pvs.Show(source, view)
    display.SetRepresentationType("Volume")
    pvs.ColorBy(display, ("POINTS", array))
    display.VolumeRenderingMode = "Ray Cast Only"
    rs = spec.rendering
    unit = rs.opacity_unit_distance
    display.ScalarOpacityUnitDistance = float(min(inputs.volume.spacing) if unit is None else unit)
    display.Shade = int(bool(rs.shade))
    set_camera(view, camera)
    return view, display


def save_screenshot(pvs, view, camera, path):
    pvs.Render(view)
    pvs.SaveScreenshot(path, view, ImageResolution=[camera.width, camera.height])
    if not os.path.isfile(path):
        raise BatchError(f"output file {path}: ParaView did not write the screenshot")


def set_transfer_functions(pvs, display, array, spec):
    """Give ``display`` the spec's colour LUT and opacity function for ``array`` (fixed range)."""
    rgb, pts = transfer_function_points(spec, data_range(display, array))
    lut = pvs.GetColorTransferFunction(array)
    lut.AutomaticRescaleRangeMode = "Never"
    lut.ColorSpace = "RGB"
    lut.RGBPoints = rgb
    pwf = pvs.GetOpacityTransferFunction(array)
    pwf.Points = pts
    display.LookupTable = lut
    display.ScalarOpacityFunction = pwf


def data_range(display, array):
    """The range of the point array ``array`` shown by ``display`` (None if unknown)."""
    try:
        info = display.Input.PointData[array]
    except (AttributeError, KeyError, TypeError):
        return None
    return None if info is None else tuple(info.GetRange())


def screenshot(pvs, source, array, inputs, path):
    """Volume-render ``source`` with the spec's transfer functions and save ``path``."""
    spec = inputs.spec
    view, display = show_volume(pvs, source, array, inputs)
    set_transfer_functions(pvs, display, array, spec)
    light = spec.structures[0].lighting
    display.Ambient, display.Diffuse = light.ambient, light.diffuse
    display.Specular, display.SpecularPower = light.specular, light.specular_power
    save_screenshot(pvs, view, inputs.camera, path)


def measure_images(pvs, output, background, out_dir):
    """Write the filter's image and deviation maps; return the paths."""
    import numpy as np
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy

    from dvr_perception._files import write_png

    w, h, _ = output.GetDimensions()
    pd = output.GetPointData()

    def image(name):  # VTK point order (bottom row first) -> rows from the top
        a = vtk_to_numpy(pd.GetArray(name))
        return a.reshape(h, w, -1)[::-1]

    rgba = image("rgba").astype(np.float64)
    hit = rgba[..., 3] > 0
    files = [os.path.join(out_dir, "image.png")]
    over = rgba[..., :3] + (1.0 - rgba[..., 3:]) * np.asarray(background, float)
    write_png(files[0], np.clip(over, 0.0, 1.0))
    lut = pvs.GetColorTransferFunction("dvr_perception_deviation")
    lut.ApplyPreset("Viridis (matplotlib)", True)
    mapper = lut.GetClientSideObject()
    for name, array, limits in DEVIATION_IMAGES:
        values = image(array)[..., 0].astype(np.float64)
        lo, hi = limits or (0.0, max(1e-3, float(values.max(initial=0.0))))
        lut.RescaleTransferFunction(lo, hi)
        mapper.Build()
        mapped = mapper.MapScalars(numpy_to_vtk(values.ravel(), deep=True), 1, -1)
        colours = vtk_to_numpy(mapped).reshape(h, w, -1)[..., :3].copy()
        colours[~hit] = 0
        path = os.path.join(out_dir, name)
        write_png(path, colours)
        files.append(path)
    return files


def field_values(output):
    fd = output.GetFieldData()
    if fd.GetArray("E_v") is None:
        raise BatchError("Perception Measures failed (see the ParaView error above)")
    result = {k: fd.GetArray(k).GetValue(0) for k in ("E_v", "E_s", "E_t")}
    names_arr = fd.GetAbstractArray("structure_names")
    names = [names_arr.GetValue(i) for i in range(names_arr.GetNumberOfValues())]
    result["structures"] = {
        n: {k: fd.GetArray(k).GetValue(i) for k in PER_STRUCTURE} for i, n in enumerate(names)
    }
    return result


def run(args):
    t0 = time.perf_counter()
    from paraview import simple as pvs

    from dvr_perception._files import write_json
    from dvr_perception.inputs import load_inputs, make_output_dir
    from dvr_perception.structures.io import spec_to_dict

    ranks = check_ranks(args.ranks)
    if ranks > 1:
        source, inputs = reader_inputs(pvs, args)
    else:
        inputs = load_inputs(args)
    out_dir = str(make_output_dir(args.out))
    pvs.LoadPlugin(PLUGIN)  # adds the filters to paraview.simple
    if ranks == 1:
        source, array = volume_source(pvs, inputs.volume, args.volume)
    else:
        array = ""  # the reader's active scalars
    measures = pvs.PerceptionMeasures(
        Input=source,
        ScalarArray=array,
        SpecJSON=json.dumps(spec_to_dict(inputs.spec)),
        CameraJSON=json.dumps(inputs.camera.to_dict()),
        Sigma=args.sigma,
        Distributed=int(ranks > 1),
    )
    measures.UpdatePipeline()
    output = pvs.servermanager.Fetch(measures)
    result = field_values(output)
    if ranks > 1:
        array = source.PointData.keys()[0]
        result["ranks"] = rank_records(output, ranks)
    files = measure_images(pvs, output, inputs.spec.background, out_dir)
    labelled = any(s.label is not None for s in inputs.spec.structures)
    if labelled and not args.no_screenshot:  # e.g. a .seg.nrrd: no intensity transfer function
        print(
            "batch_measure: no screenshot.png: ParaView's volume mapper cannot colour label "
            "structures",
            file=sys.stderr,
        )
    if not args.no_screenshot and not labelled:
        shot = os.path.join(out_dir, "screenshot.png")
        screenshot(pvs, source, array, inputs, shot)
        files.insert(0, shot)
    from paraview import servermanager

    result.update(
        volume=str(inputs.volume_source),
        spec=inputs.spec_source,
        camera=inputs.camera.to_dict(),
        sigma=args.sigma,
        paraview_version=servermanager.vtkSMProxyManager.GetParaViewSourceVersion(),
        seconds=round(time.perf_counter() - t0, 3),
    )
    result["files"] = [os.path.basename(f) for f in [*files, "result.json"]]
    write_json(os.path.join(out_dir, "result.json"), result)
    print(json.dumps({k: result[k] for k in ("E_v", "E_s", "E_t")} | {"out": out_dir}))
    return 0


def check_ranks(ranks):
    """The number of ranks: ``--ranks`` must be ParaView's number of MPI processes."""
    from paraview.modules.vtkRemotingCore import vtkProcessModule

    running = vtkProcessModule.GetProcessModule().GetNumberOfLocalPartitions()
    if ranks < 1 or ranks != running:
        raise BatchError(
            f"--ranks {ranks}: pvbatch runs on {running} MPI rank(s); start it with "
            f"'mpiexec -n {ranks} pvbatch' (dvr-perception pvbatch --ranks does)"
        )
    return ranks


def reader_inputs(pvs, args):
    """ParaView's reader of ``args.volume`` and the inputs, from the reader's header only."""
    from types import SimpleNamespace

    from dvr_perception.inputs import DEFAULT_SIZE, RenderInputs, parse_size, read_camera
    from dvr_perception.rays.camera import Camera, parse_view
    from dvr_perception.structures.io import load_spec
    from dvr_perception.structures.presets import load_preset

    size = parse_size(args.size) if args.size is not None else None
    view = parse_view(args.view) if args.view is not None else None
    camera = read_camera(args.camera, size) if args.camera is not None else None
    path = os.path.abspath(args.volume)
    if not os.path.isfile(path):
        raise BatchError(f"{args.volume}: file not found")
    if args.structures is not None:
        spec_source = args.structures
        spec = load_spec(spec_source)
    elif getattr(args, "preset", None) is not None:
        spec, spec_source = load_preset(args.preset)
    else:  # a preset pairs by the data's checksum: this rank would have to read it all
        raise BatchError(
            f"--ranks {args.ranks}: needs --structures or --preset NAME (pairing a preset by "
            f"the data's checksum, or proposing a spec, would read all of {args.volume})"
        )
    if args.shade is not None:
        from dataclasses import replace

        spec = replace(spec, rendering=replace(spec.rendering, shade=bool(args.shade)))
    from dvr_perception.volume.io import check_volume_file

    # ParaView's own reader reads the file on the ranks: the header must first pass the one
    # parse load_volume reads with (no ambiguous header, sizes within the memory limit)
    check_volume_file(path)
    reader = pvs.OpenDataFile(path)
    if reader is None:
        raise BatchError(f"{args.volume}: ParaView has no reader for it")
    reader.UpdatePipelineInformation()
    algo = reader.GetClientSideObject()
    from vtkmodules.vtkCommonDataModel import vtkDataObject
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

    info = algo.GetOutputInformation(0)
    whole = info.Get(sddp.WHOLE_EXTENT())
    spacing = info.Get(vtkDataObject.SPACING())
    origin = info.Get(vtkDataObject.ORIGIN())
    if whole is None or spacing is None or origin is None:
        raise BatchError(f"{args.volume}: not image data ({algo.GetClassName()})")
    bounds = []
    for a in range(3):
        bounds += [origin[a] + whole[2 * a] * spacing[a], origin[a] + whole[2 * a + 1] * spacing[a]]
    grid = SimpleNamespace(spacing=tuple(spacing), bounds=tuple(bounds), extent=tuple(whole))
    if camera is None:
        az, el, zoom = view if view is not None else (spec.view or (0.0, 0.0, 1.0))
        w, h = size if size is not None else (DEFAULT_SIZE, DEFAULT_SIZE)
        camera = Camera.from_view(
            tuple(bounds), azimuth=az, elevation=el, zoom=zoom, width=w, height=h
        )
    return reader, RenderInputs(grid, spec, camera, path, str(spec_source), 0.0)


def rank_records(output, ranks):
    """The per-rank records of the filter's field data (string array ``ranks``)."""
    arr = output.GetFieldData().GetAbstractArray("ranks")
    if arr is None or arr.GetNumberOfValues() != ranks:
        raise BatchError(f"the filter did not run on {ranks} ranks together")
    return [json.loads(arr.GetValue(i)) for i in range(ranks)]


def volume_source(pvs, volume, path):
    """Return a ParaView source holding ``volume`` (named after ``path``) and its array name."""
    from dvr_perception.volume.convert import to_vtk_image

    source = pvs.TrivialProducer(registrationName=os.path.basename(str(path)))
    image = to_vtk_image(volume)
    source.GetClientSideObject().SetOutput(image)
    source.UpdatePipeline()
    return source, image.GetPointData().GetScalars().GetName()


def main(argv=None, *, parse=parse_args, execute=run):
    """Run ``execute(parse(argv))``; input errors become one line on stderr and status 2."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        return execute(parse(argv))
    except Exception as exc:
        from dvr_perception.errors import DVRInputError

        if not isinstance(exc, (BatchError, DVRInputError, OSError)):
            raise
        if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
            exc = f"{exc.filename}: {exc.strerror}"
        sys.stderr.write(f"{PROG}: error: {' '.join(str(exc).split())}\n")
        return 2


if __name__ == "__main__":
    status = main()
    if status:
        # sys.exit() inside pvbatch tears the OpenGL context down in the wrong order (an X
        # "GLXBadContext" abort), so a failure leaves without interpreter teardown; success
        # returns normally and pvbatch exits with 0.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
