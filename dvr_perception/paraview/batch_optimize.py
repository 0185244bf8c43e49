"""pvbatch script: Optimize Transfer Function on one volume, with before/after renderings.

Usage (with the environment of ``dvr-perception pvbatch``: ``PYTHONPATH=paraview/pvsite``, the
repository root and ``.pvdeps``, and an X display)::

    pvbatch dvr_perception/paraview/batch_optimize.py VOLUME [--structures SPEC]
        [--view A,E[,Z] | --camera CAM]
            [--size N|WxH] [--shade|--no-shade] [--stages S] [--weights WV,WS,WT] [--seed N]
            [--max-iter N] [--resolution N] [--region X0,Y0,X1,Y1] [--ranks N] --out DIR

``dvr-perception pvbatch VOLUME --optimize`` runs it.  The input options are resolved as in
``batch_measure.py`` (under ``mpiexec -n N pvbatch ... --ranks N`` the volume is opened with
ParaView's reader, each rank reads its piece, and the filter optimises over the ranks: see
``TransferFunctionOptimizer.execute_piece``).  The plugin's *Optimize Transfer Function*
filter runs on the volume; written into DIR:

``before.png``
    ParaView's volume rendering with the spec's transfer functions and material (what
    ``batch_measure.py`` saves as ``screenshot.png``);
``after.png``
    the same view after ``apply_optimized`` (``apply_result.py``) applied the optimised spec;
``image.png`` and the three deviation maps
    the filter's output: the engine's image of the optimised spec and its deviations;
``optimized_spec.json``
    the optimised spec (for ``dvr-perception render/measure --structures``);
``optimized_preset.json``
    the optimised transfer functions as a ParaView preset;
``result.json``
    ``initial`` and ``final`` (``E_v``, ``E_s``, ``E_t``, ``E``, from the filter's field data),
    ``status``, ``iterations``, ``optimized_spec``, the camera, the files written and, with
    several ranks, ``ranks`` (one record per rank: ``rank``, ``extent``, ``voxels``,
    ``peak_rss_mb``, ``evaluations``, ...).

Errors print one line ``dvr-perception: error: ...`` on stderr and exit with status 2.
"""

import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import batch_measure as bm  # noqa: E402

TERMS = ("E_v", "E_s", "E_t", "E")


def parse_args(argv):
    import dvr_boot

    dvr_boot.bind()
    from dvr_perception._paraview_compat import setup

    try:
        setup()
    except RuntimeError as exc:
        raise bm.BatchError(str(exc)) from None
    from dvr_perception.inputs import OptionParser, add_input_args

    parser = OptionParser(prog=f"{bm.PROG} pvbatch-optimize", description=__doc__.split("\n")[0])
    add_input_args(parser)
    parser.add_argument("--stages", default="opacity,lighting,colour", help="stages in order")
    parser.add_argument("--weights", default="1,1,1", metavar="WV,WS,WT", help="w_v, w_s, w_t")
    parser.add_argument("--seed", type=int, default=0, help="seed of the annealing (default 0)")
    parser.add_argument("--max-iter", type=int, default=10, help="iterations per stage")
    parser.add_argument("--resolution", type=int, default=0, help="0: the optimiser's default")
    parser.add_argument("--region", default="", metavar="X0,Y0,X1,Y1", help="the lens (pixels)")
    parser.add_argument("--ranks", type=int, default=1, help="MPI ranks (mpiexec -n N)")
    parser.add_argument("--no-screenshot", action="store_true", help="no before/after.png")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    args = parser.parse_args(argv)
    try:
        args.weights = [float(w) for w in args.weights.split(",")]
    except ValueError:
        args.weights = []
    if len(args.weights) != 3:
        parser.error(f"--weights: expected three numbers WV,WS,WT, got {args.weights!r}")
    return args


def _strings(array):
    """The values of a vtkStringArray as a list (empty when the array is missing)."""
    if array is None:
        return []
    return [array.GetValue(i) for i in range(array.GetNumberOfValues())]


def optimizer_values(output):
    fd = output.GetFieldData()
    if fd.GetArray("E") is None or fd.GetAbstractArray("optimized_spec_json") is None:
        raise bm.BatchError("Optimize Transfer Function failed (see the ParaView error above)")
    return {
        "initial": {k: fd.GetArray(f"initial_{k}").GetValue(0) for k in TERMS},
        "final": {k: fd.GetArray(k).GetValue(0) for k in TERMS},
        "status": int(fd.GetArray("status").GetValue(0)),
        "status_message": fd.GetAbstractArray("status_message").GetValue(0),
        "why": _strings(fd.GetAbstractArray("why")),
        "iterations": int(fd.GetArray("iterations").GetValue(0)),
        "optimized_spec": json.loads(fd.GetAbstractArray("optimized_spec_json").GetValue(0)),
    }


def run(args):
    t0 = time.perf_counter()
    from apply_result import apply_optimized
    from paraview import servermanager
    from paraview import simple as pvs

    from dvr_perception._files import write_json
    from dvr_perception.inputs import load_inputs, make_output_dir
    from dvr_perception.structures.io import spec_to_dict

    ranks = bm.check_ranks(args.ranks)
    if ranks > 1:
        source, inputs = bm.reader_inputs(pvs, args)
    else:
        inputs = load_inputs(args)
    out_dir = str(make_output_dir(args.out))
    pvs.LoadPlugin(bm.PLUGIN)
    if ranks == 1:
        source, array = bm.volume_source(pvs, inputs.volume, args.volume)
    else:
        array = ""  # the reader's active scalars
    region = ""
    if args.region:
        from dvr_perception.inputs import parse_rect

        x0, y0, x1, y1 = parse_rect(args.region, inputs.camera.width, inputs.camera.height)
        region = f"rect,{x0},{y0},{x1},{y1}"
    before = os.path.join(out_dir, "before.png")
    shots = ()
    if not args.no_screenshot and ranks == 1:
        # ParaView's rendering before the optimisation, first: the X connection is opened
        # here, so a start-up failure of Debian's pvbatch (see dvr_perception.cli.pvbatch)
        # costs seconds, not the optimisation
        bm.screenshot(pvs, source, array, inputs, before)
        shots = (before,)
    opt = pvs.OptimizeTransferFunction(
        Input=source,
        ScalarArray=array,
        SpecJSON=json.dumps(spec_to_dict(inputs.spec)),
        CameraJSON=json.dumps(inputs.camera.to_dict()),
        Stages=args.stages,
        Weights=args.weights,
        Seed=args.seed,
        MaxIterations=args.max_iter,
        Resolution=args.resolution,
        Region=region,
        Distributed=int(ranks > 1),
    )
    opt.UpdatePipeline()
    output = servermanager.Fetch(opt)
    result = optimizer_values(output)
    if ranks > 1:
        array = source.PointData.keys()[0]
        result["ranks"] = bm.rank_records(output, ranks)
    spec_path = os.path.join(out_dir, "optimized_spec.json")
    write_json(spec_path, result["optimized_spec"])
    images = bm.measure_images(pvs, output, inputs.spec.background, out_dir)
    preset = os.path.join(out_dir, "optimized_preset.json")
    if args.no_screenshot:
        from dvr_perception.export import save_paraview_preset
        from dvr_perception.structures.io import spec_from_dict

        save_paraview_preset(spec_from_dict(result["optimized_spec"]), preset)
    else:
        if not shots:  # several ranks: the reader's array is known now
            bm.screenshot(pvs, source, array, inputs, before)
            shots = (before,)
        after = os.path.join(out_dir, "after.png")
        view, display = bm.show_volume(pvs, source, array, inputs)
        apply_optimized(output, display, preset_path=preset)
        bm.save_screenshot(pvs, view, inputs.camera, after)
        shots = (*shots, after)
    result.update(
        volume=str(inputs.volume_source),
        spec=inputs.spec_source,
        camera=inputs.camera.to_dict(),
        stages=args.stages,
        weights=args.weights,
        seed=args.seed,
        max_iter=args.max_iter,
        resolution=args.resolution,
        region=args.region or None,
        paraview_version=servermanager.vtkSMProxyManager.GetParaViewSourceVersion(),
        seconds=round(time.perf_counter() - t0, 3),
    )
    files = (*shots, *images, spec_path, preset, "result.json")
    result["files"] = [os.path.basename(f) for f in files]
    write_json(os.path.join(out_dir, "result.json"), result)
    summary = {"initial_E": result["initial"]["E"], "E": result["final"]["E"], "out": out_dir}
    print(json.dumps(summary))
    return 0


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    return bm.main(argv, parse=parse_args, execute=run)


if __name__ == "__main__":
    status = main()
    if status:
        # see batch_measure.py: leave without interpreter teardown after a failure
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
