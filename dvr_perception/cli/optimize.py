"""``dvr-perception optimize``: optimise opacity, lighting and colour for a readable rendering.

The command loads its inputs (as ``render`` does), runs
:func:`~dvr_perception.optimize.optimize` (Eq. 12-15 of the paper; stages ``opacity``,
``lighting``, ``colour``) with a plain-text progress bar on stderr, which also measures the
spec before and after at the user's resolution (``measures=True``: on its own renderings,
each measured while the optimiser has it at hand), and writes into ``--out``, in two steps:

1. the result, as soon as it is known, and then printed: ``before.png`` and ``after.png``,
   ``optimized_spec.json`` (a spec for ``render``/``measure --structures``),
   ``paraview_preset.json``, ``slicer.vp.json`` and ``result.json`` (what ``--json`` prints);
2. the figures (:data:`FIGURES`; skipped with ``--no-figures``): ``before_after.png`` (side by
   side, E values in the titles), the measure figures of ``measure`` for both, prefixed
   ``before_`` and ``after_``, and ``convergence.png`` (``E_v``, ``E_s``, ``E_t`` and ``E`` per
   iteration across the stages).  Drawing them (matplotlib, one core) takes longer than a
   small volume's optimisation, so the result does not wait for them.

Each step appears all at once (:meth:`~dvr_perception._files.StagedFolder.publish`); the
first removes figures an earlier run left in the folder, and the second rewrites
``result.json`` with the figures listed, so ``result.json`` always names exactly the files of
this run in the folder.  The text summary is printed after step 1; ``--json`` prints the
final ``result.json`` after step 2.  Ctrl-C or an error while the figures are drawn leaves
the result without figures.  ``timings`` in the JSON splits the run's seconds.

Ctrl-C stops the optimiser after the current iteration (the progress callback raises
``StopIteration``); the best parameters so far are written and the exit status is 0 (``status``
1 in the JSON).  A second Ctrl-C aborts.  With ``--views N`` one parameter set is optimised
for N views: the given one and orbits of it about the view-up axis by +20, -20, +40, ... degrees;
the images and measures are those of the given view, the optimiser's terms (``optimizer``) are
averaged over the views.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from dvr_perception._files import output_folder, write_json, write_png
from dvr_perception.cli import _plots
from dvr_perception.cli._backend import add_backend_arg
from dvr_perception.cli._common import (
    add_input_args,
    coverage,
    emit_json,
    load_inputs,
    log,
    log_progress,
    parse_rect,
)
from dvr_perception.cli.measure import _positive_int
from dvr_perception.errors import DVRInputError

__all__ = [
    "FIGURES",
    "VIEW_STEP",
    "add_parser",
    "optimize_and_report",
    "optimize_result",
    "run",
    "write_figures",
]

EXAMPLE = """examples:
  dvr-perception optimize phantom --size 256 --out phantom_opt
  dvr-perception optimize ../shared/data/engine.nhdr --view=30,20 --stages opacity,lighting \\
      --weights 1,0.5,1 --region 100,80,300,260 --out engine_opt --json
"""

#: Azimuth step (degrees) between the views of ``--views``.
VIEW_STEP = 20.0
#: Most views ``--views`` accepts (18 x 20 degrees: the whole orbit).
MAX_VIEWS = 18
#: Largest ``--resolution`` and ``--max-iter``.
MAX_RESOLUTION = 4096
MAX_ITER = 1000
TERMS = ("E_v", "E_s", "E_t")
#: The figures of step 2 (see the module docstring), in the order they are written.
FIGURES = (
    "before_after.png",
    *(f"{p}_{f}" for p in ("before", "after") for f in _plots.MEASURE_FIGURES),
    "convergence.png",
)


def add_parser(subparsers, parents) -> None:
    """Register the ``optimize`` sub-command."""
    p = subparsers.add_parser(
        "optimize",
        parents=parents,
        help="optimise opacity, lighting and colour against the perceptual measures",
        description="Optimise the rendering parameters of VOLUME's structures so that the "
        "rendering shows them as intended (E = w_v E_v + w_s E_s + w_t E_t, lower is better) "
        "and write before/after images, figures, the optimised spec and presets into --out.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_backend_arg(p)
    p.add_argument(
        "--stages",
        default="opacity,lighting,colour",
        metavar="S1,S2,..",
        help="stages in order (default opacity,lighting,colour)",
    )
    p.add_argument(
        "--weights", default="1,1,1", metavar="V,S,T", help="w_v,w_s,w_t >= 0 (default 1,1,1)"
    )
    p.add_argument(
        "--region",
        metavar="X0,Y0,X1,Y1",
        help="optimise for this image rectangle (pixels, y down; the lens of Sec. 6)",
    )
    p.add_argument(
        "--views",
        type=_positive_int,
        default=1,
        metavar="N",
        help=f"optimise for N views {VIEW_STEP:g} degree azimuth steps apart (default 1, at "
        f"most {MAX_VIEWS})",
    )
    p.add_argument("--seed", type=int, default=0, metavar="N", help="annealing seed (0)")
    p.add_argument(
        "--max-iter", type=_positive_int, default=10, metavar="N", help="iterations per stage"
    )
    p.add_argument(
        "--resolution",
        type=_positive_int,
        metavar="N",
        help="long side of the optimisation camera in pixels (default 96)",
    )
    p.add_argument(
        "--coverage-keep",
        type=float,
        metavar="F",
        help="share of the starting mean opacity the opacity stage must keep, in [0, 1] "
        "(default: no floor, E_v itself penalises fading; e.g. 1 forbids any fading)",
    )
    p.add_argument(
        "--objective",
        choices=("mean", "least_squares"),  # optimize.core.OBJECTIVES (imported lazily)
        default=None,
        help="what each stage minimises and may never raise: the weighted image means E "
        "(mean) or Eq. 13's least squares over the per-pixel deviations S (least_squares); "
        "default: the optimiser's",
    )
    p.add_argument(
        "--figures",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="after the result, draw the figures (before_after.png, the measure figures, "
        "convergence.png; a few seconds); --no-figures writes the result only",
    )
    p.set_defaults(run=run)


# -- option parsing ------------------------------------------------------------------------------
def _numbers(text: str, option: str, count: int, what: str) -> list[float]:
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise DVRInputError(f"{option}: expected {what}, got {text!r}")
    return values


def parse_stages(text: str) -> tuple[str, ...]:
    """Parse ``--stages`` (comma-separated names of the optimiser's stage registry)."""
    from dvr_perception.optimize import STAGES

    names = tuple(s.strip() for s in str(text).split(","))
    if not all(names):
        raise DVRInputError(f"--stages: expected comma-separated stage names, got {text!r}")
    unknown = [s for s in names if s not in STAGES]
    if unknown:
        raise DVRInputError(
            f"--stages: unknown stage(s) {', '.join(unknown)}; known: {', '.join(STAGES)}"
        )
    return names


def parse_weights(text: str) -> tuple[float, float, float]:
    """Parse ``--weights`` (three numbers >= 0, not all zero)."""
    w = _numbers(text, "--weights", 3, "three numbers w_v,w_s,w_t")
    if min(w) < 0 or max(w) <= 0:
        raise DVRInputError(f"--weights: expected numbers >= 0, not all zero, got {text!r}")
    return w[0], w[1], w[2]


def orbit(camera, degrees: float):
    """Return ``camera`` rotated by ``degrees`` about its view-up axis through the focal point."""
    from dataclasses import replace

    f = np.asarray(camera.focal_point, float)
    k = np.asarray(camera.view_up, float)
    k = k / np.linalg.norm(k)
    v = np.asarray(camera.position, float) - f
    a = math.radians(degrees)
    rot = v * math.cos(a) + np.cross(k, v) * math.sin(a) + k * np.dot(k, v) * (1 - math.cos(a))
    return replace(camera, position=tuple(f + rot))


def view_offsets(n: int) -> list[float]:
    """Azimuth offsets of the ``n - 1`` further views: +20, -20, +40, -40, ... degrees."""
    return [VIEW_STEP * (i // 2 + 1) * (1 if i % 2 == 0 else -1) for i in range(n - 1)]


# -- progress and Ctrl-C -------------------------------------------------------------------------
class Progress:
    """The optimiser callback: a plain-text progress bar on ``stream``; stops on request.

    Parameters
    ----------
    total : int
        Expected iterations (stages x max_iter; stages may converge earlier).
    stream : file, optional
        Where the bar goes (default ``sys.stderr``).
    verbose : bool
        Name the measures (``E``, ``E_v``, ``E_s``, ``E_t``); by default they are given in
        words (mismatch: visibility, shape cues, see-through).
    """

    width = 24

    def __init__(self, total: int, stream=None, verbose: bool = False) -> None:
        self.total = max(1, int(total))
        self.verbose = bool(verbose)
        self.stream = stream if stream is not None else sys.stderr
        self.stop = False
        self.drawn = False
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __call__(self, info) -> None:
        self.draw(info)
        if self.stop:
            raise StopIteration

    def draw(self, info) -> None:
        """Write one progress line for an ``IntermediateResult``."""
        n = min(info.nit, self.total)
        fill = round(self.width * n / self.total)
        bar = "#" * fill + "-" * (self.width - fill)
        t = info.terms
        if self.verbose:
            terms = (f"E {t['E']:.4f} (E_v {t['E_v']:.3f}, E_s {t['E_s']:.3f}, "
                     f"E_t {t['E_t']:.3f})")  # fmt: skip
        else:
            terms = (f"mismatch {t['E']:.3f} (visibility {t['E_v']:.3f}, shape cues "
                     f"{t['E_s']:.3f}, see-through {t['E_t']:.3f})")  # fmt: skip
        text = f"{info.stage:<8} [{bar}] {info.nit:>3}/{self.total}  {terms}"
        self.stream.write(("\r" + text) if self.tty else (text + "\n"))
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        """End the bar's line."""
        if self.drawn and self.tty:
            self.stream.write("\n")
            self.stream.flush()


@contextmanager
def stop_on_interrupt(progress: Progress):
    """While active, the first Ctrl-C asks ``progress`` to stop; a second one aborts."""

    def handler(signum, frame):
        if progress.stop:
            raise KeyboardInterrupt
        progress.stop = True
        progress.stream.write("\ninterrupted: stopping after this iteration (Ctrl-C to abort)\n")

    try:
        old = signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread: no signal handling
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


# -- measuring and writing -----------------------------------------------------------------------
def _measure(volume, spec, camera, curvature, weights, result=None, backend="auto",
             measured=None):  # fmt: skip
    """Return ``(analysis, measures, terms)`` of ``spec`` in ``camera``.

    ``result`` is the analysis when at hand (else analysed afresh), ``measured`` its
    ``all_measures`` when at hand (the optimiser's ``measures``).
    """
    from dvr_perception.cli.measure import _structures
    from dvr_perception.measures import all_measures
    from dvr_perception.rays.engine import analyze

    if result is None:
        result = analyze(volume, spec, camera, curvature=curvature, backend=backend)
        measured = None
    vis, shp, trn = all_measures(result, spec) if measured is None else measured
    terms = {"E_v": float(vis.E_v), "E_s": float(shp.E_s), "E_t": float(trn.E_t)}
    terms["E"] = float(sum(w * terms[k] for w, k in zip(weights, TERMS, strict=True)))
    keep = ("visible_share", "target_share", "assigned_share", "perceived_transparency",
            "expected_opacity")  # fmt: skip
    per = _structures(vis, trn, result.names)
    # the optimiser's coverage: mean accumulated opacity over the rays with assigned opacity
    terms["coverage"] = float(np.asarray(result.accumulated)[vis.nonempty].mean()
                              if vis.nonempty.any() else 0.0)  # fmt: skip
    terms["pixel_coverage"] = coverage(result)
    terms["structures"] = {n: {k: e[k] for k in keep} for n, e in per.items()}
    return result, (vis, shp, trn), terms


def _why(res) -> dict:
    """Per structure: the optimiser's reasons and their lines (plain, and with the measures).

    The shares are the optimiser's (those its reasons quote); ``initial`` and ``final`` hold
    the ones measured afresh at the user's size.
    """
    from dvr_perception.optimize.explain import explanation_lines

    out = {}
    for name, entry in res.structures.items():
        e = dict(entry)
        e["lines"] = explanation_lines(name, e)
        e["lines_verbose"] = explanation_lines(name, e, verbose=True)
        e["line"] = "; ".join(e["lines"])
        out[name] = e
    return out


def _terms(d: dict) -> dict:
    return {k: float(d[k]) for k in (*TERMS, "E", "S") if k in d}


def optimize_result(volume, spec, camera, out_dir, *, stages=("opacity", "lighting", "colour"),
                    weights=(1.0, 1.0, 1.0), region=None, views=1, seed=0, max_iter=10,
                    resolution=None, coverage_keep=None, progress=None, objective=None,
                    final_dir=None, backend="auto") -> tuple[dict, dict]:  # fmt: skip
    """Optimise ``spec`` for ``camera``, write the result (step 1) into ``out_dir``.

    ``region`` is ``(x0, y0, x1, y1)`` in pixels or ``None``; ``progress`` a :class:`Progress`
    (or any callback); ``objective`` ``"mean"`` or ``"least_squares"`` (``None``: the
    optimiser's default).  ``final_dir`` is the folder the files end up in when ``out_dir`` is
    a staging folder (the optimised spec's ``labels`` path is made relative to it).
    ``backend``: the ray analyses' (:func:`~dvr_perception.rays.engine.analyze`).  See the
    module docstring for the files and the report.

    Returns
    -------
    report : dict
        What ``result.json`` holds (written into ``out_dir``); ``figures`` is empty.
    drawing : dict
        What :func:`write_figures` draws the figures from.
    """
    from dvr_perception.export import save_paraview_preset, save_slicer_vp
    from dvr_perception.optimize import optimize
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.structures.io import save_spec

    t_start = time.perf_counter()
    cameras = [orbit(camera, d) for d in view_offsets(views)]
    log.info("optimising %s at %dx%d", ",".join(stages), camera.width, camera.height)
    res = optimize(
        volume,
        spec,
        camera,
        stages=tuple(stages),
        weights=tuple(weights),
        region=None if region is None else ("rect", *region),
        cameras=cameras or None,
        seed=seed,
        callback=progress,
        progress=log_progress("curvature and first ray analyses"),
        max_iter=max_iter,
        resolution=resolution,
        coverage_keep=coverage_keep,
        backend=backend,
        measures=True,
        **({} if objective is None else {"objective": objective}),
    )
    if isinstance(progress, Progress):
        progress.close()
    t_optimised = time.perf_counter()
    log.info("measuring before and after")
    # the optimiser's renderings of the view (equal to fresh analyses), else analyse again
    first, last = res.analyses or (None, None)
    got_before, got_after = res.measures or (None, None)
    curvature = None if res.analyses else curvature_source(volume, spec)
    # (the optimiser measured both renderings where they were at hand: no second measuring)
    after, m_after, final = _measure(volume, res.spec, camera, curvature, weights, last, backend,
                                     got_after)  # fmt: skip
    before, m_before, initial = _measure(volume, spec, camera, curvature, weights, first,
                                         backend, got_before)  # fmt: skip
    t_measured = time.perf_counter()
    d = Path(out_dir)
    files = [write_png(d / "before.png", before.image), write_png(d / "after.png", after.image)]
    save_spec(res.spec, d / "optimized_spec.json", relative_to=final_dir)
    files.append(d / "optimized_spec.json")
    notes = []
    for name, save in (
        ("paraview_preset.json", lambda p: save_paraview_preset(res.spec, p)),
        ("slicer.vp.json", lambda p: save_slicer_vp(res.spec, p, volume)),
    ):
        try:
            files.append(save(d / name))
        except DVRInputError as exc:  # e.g. label structures: no intensity transfer function
            notes.append(f"{name} not written: {exc}")
    stages_out = [
        {"name": s.name, "before": _terms(s.terms_before), "after": _terms(s.terms_after),
         "iterations": s.iterations, "evaluations": s.evaluations, "seconds": s.seconds,
         "converged": s.converged, "accepted": s.accepted, "message": s.message,
         "params_after": s.params_after}
        for s in res.stages
    ]  # fmt: skip
    files.append(d / "result.json")
    why = _why(res)
    report = {
        "size": [camera.width, camera.height],
        "weights": list(weights),
        "stages_requested": list(stages),
        "views": views,
        "region": None if region is None else list(region),
        "seed": seed,
        "initial": initial,
        "final": final,
        "objective": objective,
        "optimizer": {"initial": _terms(res.initial), "final": _terms(res.final)},
        "stages": stages_out,
        "structures": why,
        "nit": res.nit,
        "nfev": res.nfev,
        "seconds_optimize": res.seconds,
        "seconds": None,
        "status": res.status,
        "message": res.message,
        "notes": notes,
        "out_dir": str(d),
        "files": [str(f) for f in files],
        "figures": [],
        "camera": camera.to_dict(),
    }
    t_end = time.perf_counter()
    report["timings"] = {
        "optimise": t_optimised - t_start,
        "measure": t_measured - t_optimised,
        "write": t_end - t_measured,
    }
    report["seconds"] = t_end - t_start
    write_json(d / "result.json", report)
    titles = [
        f"{label}: E {t['E']:.4f} (E_v {t['E_v']:.3f}, E_s {t['E_s']:.3f}, E_t {t['E_t']:.3f})"
        for label, t in (("before", initial), ("after", final))
    ]
    records = [
        {"name": s.name, "history": s.history, "before": s.terms_before, "after": s.terms_after}
        for s in res.stages
    ]
    drawing = {
        "images": [before.image, after.image],
        "titles": titles,
        "measures": {"before": m_before, "after": m_after},
        "records": records,
        "title": f"optimisation ({res.nit} iterations, {res.message})",
    }
    return report, drawing


def write_figures(out_dir, drawing: dict) -> list[Path]:
    """Draw the figures (step 2, :data:`FIGURES`) of :func:`optimize_result` into ``out_dir``.

    Returns
    -------
    list of pathlib.Path
        The written files, in the order of :data:`FIGURES`.
    """
    d = Path(out_dir)
    files = [_plots.save_side_by_side(d / FIGURES[0], drawing["images"], drawing["titles"])]
    for prefix in ("before", "after"):
        files += _plots.save_measure_figures(d, prefix, drawing["measures"][prefix])
    files.append(_plots.save_convergence(d / FIGURES[-1], drawing["records"],
                                         title=drawing["title"]))  # fmt: skip
    return files


def _add_figures(report: dict, figures, seconds: float) -> dict:
    """``report`` with the figures listed (before ``result.json``) and their seconds."""
    names = [str(f) for f in figures]
    files = list(report["files"])
    at = len(files) - 1 if files and files[-1].endswith("result.json") else len(files)
    timings = {**report.get("timings", {}), "figures": seconds}
    return {**report, "files": [*files[:at], *names, *files[at:]], "figures": names,
            "timings": timings, "seconds": report["seconds"] + seconds}  # fmt: skip


def optimize_and_report(volume, spec, camera, out_dir, *, figures=True, **kwargs) -> dict:
    """Optimise ``spec`` for ``camera``, write every output into ``out_dir``, return the report.

    :func:`optimize_result` (its keyword arguments) and, with ``figures``,
    :func:`write_figures` in one step (``result.json`` lists the figures); see the module
    docstring for the files and the report.
    """
    report, drawing = optimize_result(volume, spec, camera, out_dir, **kwargs)
    if not figures:
        return report
    t0 = time.perf_counter()
    written = write_figures(out_dir, drawing)
    report = _add_figures(report, written, time.perf_counter() - t0)
    write_json(Path(out_dir) / "result.json", report)
    return report


def _since_start() -> float | None:
    """Seconds since this process started (Linux's ``/proc``), or None where unknown."""
    try:
        stat = Path("/proc/self/stat").read_text()
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        ticks = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, AttributeError):
        return None
    start = float(stat.rsplit(")", 1)[1].split()[19]) / ticks  # field 22: starttime
    return max(0.0, uptime - start)


def _sleeping_openmp_threads() -> None:
    """Let numba's idle OpenMP threads sleep at once (unless the environment says otherwise).

    The optimiser launches hundreds of short parallel regions (re-composites, measures),
    some from the measures' worker thread.  After each, GNU OpenMP's threads spin for a
    while by default, and only throttle that when more threads than cores are in use, so
    the spinning depended on whether the worker thread happened to launch a region: on a
    busy machine it burnt a core the calling thread needed.  ``OMP_WAIT_POLICY=PASSIVE``
    (read when numba first starts its threads, after this) makes every run alike.
    """
    if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"


def run(args: argparse.Namespace) -> int:
    """Execute ``optimize``."""
    _sleeping_openmp_threads()
    stages = parse_stages(args.stages)
    weights = parse_weights(args.weights)
    if args.seed < 0:
        raise DVRInputError(f"--seed: expected an integer >= 0, got {args.seed}")
    keep = args.coverage_keep
    if keep is not None and not (0.0 <= keep <= 1.0):
        raise DVRInputError(f"--coverage-keep: expected a number in [0, 1], got {keep:g}")
    if args.region is not None and args.views > 1:
        raise DVRInputError("--region refines one view; use it without --views")
    for option, value, top in (
        ("--views", args.views, MAX_VIEWS),
        ("--resolution", args.resolution, MAX_RESOLUTION),
        ("--max-iter", args.max_iter, MAX_ITER),
    ):
        if value is not None and value > top:
            raise DVRInputError(f"{option}: expected 1 to {top}, got {value}")
    startup = _since_start()  # the interpreter and the imports before this call
    t0 = time.perf_counter()
    inputs = load_inputs(args)
    cam = inputs.camera
    region = None if args.region is None else parse_rect(args.region, cam.width, cam.height)
    verbose = bool(getattr(args, "verbose", False))
    loaded = time.perf_counter() - t0
    # checked and locked before the work; the result appears all at once, then the figures
    with output_folder(args.out) as staged:
        progress = Progress(len(stages) * args.max_iter, verbose=verbose)
        with stop_on_interrupt(progress):
            report, drawing = optimize_result(inputs.volume, inputs.spec, cam, staged.path,
                                              stages=stages, weights=weights, region=region,
                                              views=args.views, seed=args.seed,
                                              max_iter=args.max_iter,
                                              resolution=args.resolution,
                                              coverage_keep=args.coverage_keep,
                                              progress=progress, objective=args.objective,
                                              final_dir=staged.final,
                                              backend=args.backend)  # fmt: skip
        report = {"volume": inputs.volume_source, "spec": inputs.spec_source, **report}
        report["out_dir"] = str(staged.final)
        report["files"] = [str(staged.final_path(f)) for f in report["files"]]
        report["timings"] = {"startup": startup, "load": loaded, **report["timings"]}
        write_json(staged.path / "result.json", report)
        staged.publish(stale=FIGURES)  # the result is in the folder now
        if not args.json:
            print_summary(report, verbose=verbose, figures=args.figures)
            sys.stdout.flush()
        if args.figures:
            log.info("drawing %d figures", len(FIGURES))
            t0 = time.perf_counter()
            written = write_figures(staged.path, drawing)
            seconds = time.perf_counter() - t0
            report = _add_figures(report, [staged.final_path(f) for f in written], seconds)
            write_json(staged.path / "result.json", report)
    if args.json:
        emit_json(report)
    elif args.figures:
        print(f"  figures: wrote {len(report['figures'])} more files ({seconds:.1f} s)")
    return 0


#: ``status`` -> what the default text says (the codes and the optimiser's own messages are
#: under ``-v`` and in ``--json``).
PLAIN_STATUS = {
    0: "finished: every stage settled on its best setting",
    1: "stopped on request: the best settings found so far were kept",
    2: "stopped at the step limit (--max-iter) before every stage settled: the best settings "
    "found were kept",
}
#: The measures in plain words (default text), in the order of ``TERMS``.
PLAIN_TERMS = ("visibility", "shape cues", "see-through")


def _plain_stage(s: dict) -> str:
    """Say what a stage did, without the measures' names."""
    msg = str(s.get("message", ""))
    if not s.get("accepted", True):
        what = "undone: the result did not hold at full size"
    elif msg.startswith("improved, with the step cut"):
        what = "improved (with a shortened step, which held at full size)"
    elif msg.startswith("improved"):
        what = "improved"
    elif msg.startswith("no feasible"):
        what = "no better setting found; unchanged"
    else:
        what = msg
    return f"{s['name']}: {what} ({s['iterations']} steps, {s['seconds']:.1f} s)"


def print_summary(report: dict, *, indent: str = "  ", verbose: bool = False,
                  figures: bool = False) -> None:  # fmt: skip
    """Print the result on stdout: plain words by default, the measures with ``verbose``.

    The default text names no measure (``E_v``, ``E_s``, ``E_t``, Eq. 13's ``S``) and no
    status code: it gives the mismatch with the intended picture in words, what each stage
    did, one consistent reason per structure with its shading and colour changes
    (:func:`~dvr_perception.optimize.explain.explanation_lines`) and how the run ended.
    ``verbose`` (``-v``) prints the measures, the stages' ``E``, Eq. 13's ``S`` and the status
    code as well, and the split of the seconds (``timings``).  ``figures``: the figures are
    still to be drawn (said on the last line).
    """
    from dvr_perception.structures.spec import printable

    a, b = report["initial"], report["final"]
    w, h = report["size"]
    volume = printable(report.get("volume", "the volume"))
    if verbose:
        print(f"optimised {volume} ({w}x{h}, weights {report['weights']})")
        print(f"{indent}{'':8}{'E_v':>9}{'E_s':>9}{'E_t':>9}{'E':>9}")
        for label, t in (("before", a), ("after", b)):
            print(f"{indent}{label:8}" + "".join(f"{t[k]:9.4f}" for k in (*TERMS, "E")))
        for s in report["stages"]:
            print(
                f"{indent}stage {s['name']:<9} E {s['before']['E']:.4f} -> {s['after']['E']:.4f}"
                f"  ({s['iterations']} it, {s['seconds']:.1f} s; {s['message']})"
            )
    else:
        print(f"optimised {volume} ({w}x{h})")
        parts = ", ".join(
            f"{word} {a[k]:.2f} -> {b[k]:.2f}" for word, k in zip(PLAIN_TERMS, TERMS, strict=True)
        )
        print(f"{indent}mismatch with the intended picture (lower is better): {parts}; overall "
              f"{a['E']:.2f} -> {b['E']:.2f}")  # fmt: skip
        if report.get("objective"):
            judged = {
                "mean": "the picture's mean mismatch",
                "least_squares": "each pixel's mismatch, squared (least squares)",
            }
            print(f"{indent}judged by {judged.get(report['objective'], report['objective'])}")
        for s in report["stages"]:
            print(f"{indent}{_plain_stage(s)}")
    structures = report.get("structures", {})
    if structures:
        print(f"{indent}what changed and why:")
    for entry in structures.values():
        lines = entry.get("lines_verbose" if verbose else "lines") or [entry["line"]]
        print(f"{indent}{indent}{printable(lines[0])}")
        for line in lines[1:]:
            print(f"{indent}{indent}{indent}{printable(line)}")
    if verbose:
        opt = report.get("optimizer", {})
        if "S" in opt.get("initial", {}):
            which = report.get("objective") or "default"
            print(f"{indent}S (Eq. 13) {opt['initial']['S']:.4f} -> {opt['final']['S']:.4f}; "
                  f"objective {which}")  # fmt: skip
        print(f"{indent}status {report['status']}: {report['message']}")
    else:
        print(f"{indent}{PLAIN_STATUS.get(report['status'], report['message'])}")
    for note in report["notes"]:
        print(f"{indent}note: {note}")
    if verbose and report.get("timings"):
        split = ", ".join(f"{k} {v:.2f}" for k, v in report["timings"].items() if v is not None)
        print(f"{indent}seconds by step: {split}")
    more = "; the figures follow (--no-figures skips them)" if figures else ""
    print(f"{indent}seconds {report['seconds']:.1f}; wrote {len(report['files'])} files into "
          f"{printable(report['out_dir'])}/{more}")  # fmt: skip
