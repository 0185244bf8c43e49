"""``dvr-perception bench``: time our engine against VTK's CPU volume ray caster.

Reported figures (seconds unless stated):

* ``load_s`` – reading (or generating) the volume, and up-sampling it with ``--resample
  FX,FY,FZ`` (integer factors along x, y, z, trilinear; e.g. ``--resample 2,2,4`` turns
  cthead's 256×256×113 into 512×512×452); ``--save-volume PATH`` also writes that volume
  (e.g. ``big/cthead.nhdr``; its data are not cthead's, so give it ``--preset cthead``) for
  the other commands.
* ``curvature_s`` – the curvature volume; ``curvature_vtk_frames`` = ``curvature_s /
  vtk_frame_s``.
* ``peak_rss_mb`` – the process's peak resident memory (``ru_maxrss``) at the end, MiB: the
  engine's, since VTK renders in a child process (:func:`~dvr_perception.rays.vtk_process.
  vtk_frame_process`);
  ``vtk_peak_rss_mb`` – that child's peak (``VmHWM``: VTK's renderer with its copy of the
  volume); ``peak_rss_vtk_ratio`` = ``peak_rss_mb / vtk_peak_rss_mb``.
* ``compile_s`` – the first, warm-up :func:`~dvr_perception.rays.engine.analyze` call (numba
  compilation included); ``frame_s`` – median of ``--repeat`` further full analyses (every
  buffer the measures read, ``analyze``'s default: no re-evaluation cache, and behind early
  ray termination only what can change a result is walked, DECISIONS D8);
  ``frame_cache_s`` – the same analysis building the re-evaluation cache (``build_cache=True``,
  what an optimiser's or a slider's first frame costs: that walk visits every sample behind
  early ray termination), ``frame_cache_ratio`` = ``frame_cache_s / vtk_frame_s``.
* ``vtk_frame_s`` – median of ``--repeat`` warm frames of VTK's fixed-point ray caster, same
  view and size (:func:`~dvr_perception.rays.vtk_reference.vtk_frame_timer`, in the child
  process; the child times its frames), timed alternately with ours so that both see the
  same machine load; ``frame_ratio`` = ``frame_s / vtk_frame_s``.
* ``render_s`` – median frame of the image alone (``analyze(..., build_cache=False,
  occlusion_free=False)``: rays stop at early ray termination as VTK's do; what ``render``
  without ``--buffers`` pays), timed in turn with the two above; ``render_ratio`` =
  ``render_s / vtk_frame_s``.  ``frame_s - render_s`` is the price of the occlusion-free
  shares behind early ray termination.
* ``reeval_s`` – median :func:`~dvr_perception.rays.engine.reevaluate` of the cache with
  perturbed opacities (what one optimiser step costs); ``reeval_vtk_frames`` =
  ``reeval_s / vtk_frame_s``.
* ``samples_per_s`` – ray samples per second of a full frame; ``cache_mb`` – size of the
  re-evaluation cache.
* ``backend`` – the back end that analysed (``--backend``, default ``auto``: ``cuda`` where
  numba finds a CUDA device, else ``numba``); the same keys on every back end (with
  ``cuda`` the re-evaluations still composite the cache on the CPU).
* ``measure_s`` – median time of the three measures (visibility, shape, transparency, as
  :func:`~dvr_perception.measures.all_measures` computes them), each run on a fresh analysis
  (the measures remember checked fields and the luminance on the analysis they were given);
  ``measure_total_s`` – median of what ``dvr-perception measure`` pays per view once the
  curvature volume exists: :func:`~dvr_perception.rays.engine.analyze` (no re-evaluation
  cache), then the measures (an enclosing layer's view without it walked again, D7), timed
  in turn with VTK's frames as above;
  ``measure_vtk_frames`` = ``measure_total_s / vtk_frame_s``; ``recomposite_s`` – inside it,
  the walk of the enclosing layers' pixels without them (D7's extra cost; every encloser of
  the view in one walk, run beside visibility and shape), ``recomposite_vtk_frames``, and the
  ``recomposite_layers``, ``recomposite_rays`` and ``recomposite_mb`` it walked and returned.
* with ``--optimize``: ``optimize_s`` – one whole :func:`~dvr_perception.optimize.optimize`
  run with the default stages (opacity, lighting, colour) and the curvature volume passed in
  (it is ``curvature_s`` above and does not depend on the optimised parameters);
  ``optimize_vtk_frames`` = ``optimize_s / vtk_frame_s``; ``optimize_with_curvature_s`` adds
  ``curvature_s``; ``iteration_s`` – per stage, seconds per iteration; ``optimize_stages`` –
  per stage ``E`` and its lead term before and after, iterations, evaluations, seconds and
  whether it was kept; ``optimize_terms`` – the terms before and after (user's resolution).
* ``bricked`` – whether any timed analysis was bricked (the memory plan,
  :func:`~dvr_perception.rays.memory.plan`: the whole volume whenever it fits the limit);
  ``bricks`` – per timed analysis (``frame``, ``render``, ``measure``) the bricks it walked,
  0 for the whole volume.  ``samples`` – the ray samples of a full frame (inside the volume);
  ``samples_walked`` and ``samples_walked_skipping`` – those the full analysis (``frame``)
  visited (behind early ray termination it skips what cannot change a result, DECISIONS
  D8); ``samples_walked_cache`` – those the cache-building walk visited (every sample);
  ``samples_walked_exact`` – those the analysis visits with ``exact=True`` (the full walk;
  one more analysis, not timed).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import statistics
import time

import numpy as np

from dvr_perception._files import file_lock
from dvr_perception._timing import median_time as _median_time
from dvr_perception.cli._backend import add_backend_arg
from dvr_perception.cli._common import (
    add_input_args,
    check_output_file,
    emit_json,
    load_inputs,
    log,
    parse_factors,
)

__all__ = ["MAX_REPEAT", "add_parser", "run"]

#: Most ``--repeat`` (timed frames of each kind; a median of more says nothing new).
MAX_REPEAT = 100

EXAMPLE = """examples:
  dvr-perception bench --json
  dvr-perception bench ../shared/data/engine.nhdr --size 512 --repeat 3 --json
  dvr-perception bench ../shared/data/cthead.nhdr --resample 2,2,4 --repeat 1 --json
  dvr-perception bench ../shared/data/cthead.nhdr --resample 2,2,4 --save-volume big/cthead.nhdr
"""


def add_parser(subparsers, parents) -> None:
    """Register the ``bench`` sub-command."""
    p = subparsers.add_parser(
        "bench",
        parents=parents,
        help="time full frames and opacity re-evaluations against VTK",
        description="Benchmark the ray-analysis engine on VOLUME (default: the phantom).",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_args(p, volume_optional=True)
    add_backend_arg(p)
    p.add_argument(
        "--repeat",
        type=int,
        default=5,
        metavar="R",
        help=f"timed repeats (default 5, at most {MAX_REPEAT})",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the opacity perturbation (default 0)"
    )
    p.add_argument(
        "--resample",
        metavar="FX,FY,FZ",
        help="up-sample the volume by integer factors along x, y, z (or one factor F)",
    )
    p.add_argument(
        "--save-volume",
        metavar="PATH",
        help="also write the (up-sampled) volume to PATH (.nhdr, .nrrd, .vti, ...)",
    )
    p.add_argument(
        "--optimize",
        action="store_true",
        help="also time one whole 3-stage optimisation (opacity, lighting, colour)",
    )
    p.set_defaults(run=run)


def _nbytes(obj, seen=None) -> int:
    """Bytes held in NumPy arrays reachable from ``obj`` (dataclass, dict, list, object)."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return int(obj.nbytes)
    if hasattr(obj, "nbytes") and isinstance(obj.nbytes, (int, np.integer)):
        return int(obj.nbytes)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        items = [getattr(obj, f.name) for f in dataclasses.fields(obj)]
    elif isinstance(obj, dict):
        items = list(obj.values())
    elif isinstance(obj, (list, tuple)):
        items = list(obj)
    elif hasattr(obj, "__dict__"):
        items = list(vars(obj).values())
    else:
        return 0
    return sum(_nbytes(v, seen) for v in items)


def _peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (``ru_maxrss``: KiB on Linux, B on macOS)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10


def _paired_frames(ours: dict, inputs, repeat: int) -> tuple:
    """Median seconds of each of our frames and of VTK's, timed in turn on the same machine.

    ``ours`` maps a name to a function rendering one frame.  Returns ``(ours, vtk_s, error,
    vtk_peak_rss_mb)``: when VTK cannot render here, VTK's time is ``None`` and the reason is
    returned; the peak memory of VTK's process is known when it rendered in a child.
    """
    from dvr_perception.errors import DVRInputError
    from dvr_perception.rays.vtk_process import vtk_frame_process

    mine: dict[str, list] = {name: [] for name in ours}
    theirs: list = []

    def ours_once():
        for name, fn in ours.items():
            mine[name].append(_median_time(fn, 1))

    try:
        # VTK renders in a child process: its memory apart from ours
        with vtk_frame_process(inputs.volume, inputs.spec, inputs.camera) as vtk_frame:
            for _ in range(repeat):
                theirs.append(vtk_frame())
                ours_once()
    except DVRInputError as exc:  # VTK cannot render here: report, do not fail the bench
        while min(len(v) for v in mine.values()) < repeat:
            ours_once()
        mine_s = {n: float(statistics.median(v[-repeat:])) for n, v in mine.items()}
        return mine_s, None, str(exc), None
    return (
        {n: float(statistics.median(v)) for n, v in mine.items()},
        float(statistics.median(theirs)),
        None,
        getattr(vtk_frame, "peak_rss_mb", None),
    )


def _samples(stats: dict):
    for key in ("samples", "n_samples", "samples_total"):
        if key in stats:
            return float(stats[key])
    return None


def _measure_times(make_analysis, spec, repeat: int) -> float:
    """Median seconds of the three measures alone (``measure_s``), each on a fresh analysis.

    A fresh analysis per run: the measures remember checked fields and the luminance on an
    analysis, so timing them again on the same one would leave that work out.
    """
    from dvr_perception.measures import all_measures

    log.info("%d timed measure runs", repeat)
    times = []
    for _ in range(repeat):
        analysis = make_analysis()
        t0 = time.perf_counter()
        all_measures(analysis, spec)
        times.append(time.perf_counter() - t0)
    return float(statistics.median(times))


def _recomposite_report(runs: list, vtk_frame_s) -> dict:
    """D7's extra cost in ``measure``: the walks of the enclosers' pixels without them.

    ``runs``: per timed measure, :func:`~dvr_perception.rays.engine.recomposites` of its
    analysis.  Median seconds over the runs (all the enclosers of a view walk together),
    and the layers, rays and bytes of the last run.
    """
    if not runs:
        return {}
    last = runs[-1]
    seconds = float(statistics.median([sum(r["seconds"] for r in run) for run in runs]))
    return {
        "recomposite_s": seconds,
        "recomposite_vtk_frames": seconds / vtk_frame_s if vtk_frame_s else None,
        "recomposite_layers": int(sum(r["layers"] for r in last)),
        "recomposite_rays": int(sum(r["rays"] for r in last)),
        "recomposite_mb": sum(r["bytes"] for r in last) / 2**20,
    }


def _optimize_report(vol, spec, cam, curv, seed: int, backend: str = "auto") -> dict:
    """Time one default :func:`~dvr_perception.optimize.optimize` run (see the module doc)."""
    from dvr_perception.optimize import optimize
    from dvr_perception.optimize.stages import STAGES

    log.info("3-stage optimisation")
    t0 = time.perf_counter()
    res = optimize(vol, spec, cam, curvature=curv, seed=seed, backend=backend)
    optimize_s = time.perf_counter() - t0
    keys = ("E_v", "E_s", "E_t", "E", "coverage")
    stages = {}
    for rec in res.stages:
        lead = STAGES[rec.name].lead
        stages[rec.name] = {
            "E_before": rec.terms_before["E"],
            "E_after": rec.terms_after["E"],
            "lead": lead,
            "lead_before": rec.terms_before[lead],
            "lead_after": rec.terms_after[lead],
            "iterations": rec.iterations,
            "evaluations": rec.evaluations,
            "seconds": rec.seconds,
            "kept": rec.accepted,
            "message": rec.message,
        }
    return {
        "optimize_s": optimize_s,
        "iteration_s": {r.name: r.seconds / max(r.iterations, 1) for r in res.stages},
        "optimize_nfev": res.nfev,
        "optimize_stages": stages,
        "optimize_terms": {
            "initial": {k: res.initial[k] for k in keys},
            "final": {k: res.final[k] for k in keys},
        },
    }


def run(args: argparse.Namespace) -> int:
    """Execute ``bench``."""
    from dvr_perception.errors import DVRInputError

    if args.repeat < 1:
        raise DVRInputError(f"--repeat: expected a positive integer, got {args.repeat}")
    if args.repeat > MAX_REPEAT:
        raise DVRInputError(f"--repeat: expected at most {MAX_REPEAT}, got {args.repeat}")
    import numba

    from dvr_perception.rays.curvature_field import CurvatureField, curvature_source
    from dvr_perception.rays.engine import analyze, recomposites, reevaluate, release_scratch

    analyze = functools.partial(analyze, backend=args.backend)  # every frame on that back end
    with contextlib.ExitStack() as held:
        if args.save_volume is not None:
            check_output_file(args.save_volume)
            held.enter_context(file_lock(args.save_volume))  # a second run is refused
        inputs = load_inputs(args)
        vol, spec, cam = inputs.volume, inputs.spec, inputs.camera
        if args.save_volume is not None:
            from dvr_perception.volume.io import save_volume

            log.info("writing %s", args.save_volume)
            save_volume(vol, args.save_volume)
    log.info("curvature volume")
    t0 = time.perf_counter()
    curv = curvature_source(vol, spec)  # per brick (inside the frames) when too large
    if isinstance(curv, CurvatureField):
        curv.globals  # noqa: B018 - the whole-volume pass, timed here
    curvature_s = time.perf_counter() - t0

    log.info("warm-up frame (compiles numba kernels)")
    t0 = time.perf_counter()
    warm = analyze(vol, spec, cam, curvature=curv)
    compile_s = time.perf_counter() - t0
    log.info("%d timed frames, ours and VTK's alternately", args.repeat)
    from dvr_perception.measures import all_measures

    all_measures(warm, spec)  # compiles the measures' kernels (and the re-walk's)
    del warm  # one analysis at a time: the peak memory is a frame's, not two frames'
    analyze(vol, spec, cam, build_cache=False, occlusion_free=False)  # compiles that variant
    analyze(vol, spec, cam, curvature=curv, build_cache=True)  # and the cache's
    bricks: dict[str, int] = {}  # per timed analysis: bricks walked (0: the whole volume)
    walked_by: dict[str, int] = {}  # per timed analysis: samples its walk visited

    walked_again: list[list[dict]] = []  # per timed measure: D7's walks without enclosers

    def measure_once():
        analysis = counted("measure", analyze(vol, spec, cam, curvature=curv, build_cache=False))
        out = all_measures(analysis, spec)
        walked_again.append(recomposites(analysis))
        return out

    def counted(name, analysis):
        bricks[name] = int(analysis.stats.get("bricks", 0))
        walked_by[name] = int(analysis.stats.get("samples_walked", 0))
        return analysis

    frames, vtk_frame_s, vtk_error, vtk_peak = _paired_frames(
        {
            "frame": lambda: counted("frame", analyze(vol, spec, cam, curvature=curv)),
            "frame_cache": lambda: counted(
                "frame_cache", analyze(vol, spec, cam, curvature=curv, build_cache=True)
            ),
            "render": lambda: counted(
                "render", analyze(vol, spec, cam, build_cache=False, occlusion_free=False)
            ),
            # what ``dvr-perception measure`` pays per view once the curvature volume exists
            "measure": measure_once,
        },
        inputs,
        args.repeat,
    )
    frame_s, render_s, measure_total_s = frames["frame"], frames["render"], frames["measure"]
    frame_cache_s = frames["frame_cache"]

    # what the re-evaluations start from; as the optimiser, once its views are analysed, the
    # walk's scratch goes back (no cache is built while re-evaluating)
    result = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    release_scratch()
    base = np.array([s.render_opacity for s in spec.structures], float)
    rng = np.random.default_rng(args.seed)

    def reeval(cache):
        ops = np.clip(base * rng.uniform(0.8, 1.2, base.shape), 0.01, 1.0)
        reevaluate(cache, opacities=ops)

    reeval(result.cache)  # compiles the re-evaluation kernels
    reeval_s = _median_time(functools.partial(reeval, result.cache), args.repeat)
    samples = _samples(result.stats)
    backend = result.stats.get("backend", "auto")
    cache_mb = _nbytes(result.cache) / 2**20
    del result  # the optimisation below holds its own caches
    measure_s = _measure_times(
        lambda: analyze(vol, spec, cam, curvature=curv, build_cache=False), spec, args.repeat
    )
    exact = analyze(vol, spec, cam, curvature=curv, build_cache=False, exact=True)
    walked_exact = int(exact.stats["samples_walked"])
    del exact

    report = {
        "volume": inputs.volume_source,
        "spec": inputs.spec_source,
        "dims": list(vol.dims),
        "size": [cam.width, cam.height],
        "structures": len(spec.structures),
        "backend": backend,
        "numba_threads": int(numba.get_num_threads()),
        "load_s": inputs.load_s,
        "curvature_s": curvature_s,
        "compile_s": compile_s,
        "frame_s": frame_s,
        "vtk_frame_s": vtk_frame_s,
        "frame_ratio": frame_s / vtk_frame_s if vtk_frame_s else None,
        "frame_cache_s": frame_cache_s,
        "frame_cache_ratio": frame_cache_s / vtk_frame_s if vtk_frame_s else None,
        "samples_per_s": samples / frame_s if samples is not None else None,
        "render_s": render_s,
        "render_ratio": render_s / vtk_frame_s if vtk_frame_s else None,
        "reeval_s": reeval_s,
        "reeval_vtk_frames": reeval_s / vtk_frame_s if vtk_frame_s else None,
        "cache_mb": cache_mb,
        "measure_s": measure_s,
        "measure_total_s": measure_total_s,
        "measure_vtk_frames": measure_total_s / vtk_frame_s if vtk_frame_s else None,
        **_recomposite_report(walked_again, vtk_frame_s),
        "repeat": args.repeat,
        "resample": list(parse_factors(args.resample)) if args.resample is not None else None,
        "curvature_vtk_frames": curvature_s / vtk_frame_s if vtk_frame_s else None,
        "bricked": any(bricks.values()),
        "bricks": bricks,
        "samples": int(samples) if samples is not None else None,
        "samples_walked": walked_by.get("frame"),
        "samples_walked_skipping": walked_by.get("frame"),
        "samples_walked_cache": walked_by.get("frame_cache"),
        "samples_walked_exact": walked_exact,
    }
    if vtk_error is not None:
        report["vtk_error"] = vtk_error
    if args.optimize:
        opt = _optimize_report(vol, spec, cam, curv, args.seed, args.backend)
        frames = opt["optimize_s"] / vtk_frame_s if vtk_frame_s else None
        opt["optimize_vtk_frames"] = frames
        opt["optimize_with_curvature_s"] = opt["optimize_s"] + curvature_s
        report.update(opt)
    report["peak_rss_mb"] = _peak_rss_mb()
    report["vtk_peak_rss_mb"] = vtk_peak
    report["peak_rss_vtk_ratio"] = report["peak_rss_mb"] / vtk_peak if vtk_peak else None
    if args.json:
        emit_json(report)
    else:
        for key, value in report.items():
            print(f"{key:>18}: {value:.4g}" if isinstance(value, float) else f"{key:>18}: {value}")
    return 0
