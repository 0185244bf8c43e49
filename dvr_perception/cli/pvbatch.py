"""``dvr-perception pvbatch``: the Perception Measures of one volume, computed inside ParaView.

Runs ``paraview/batch_measure.py`` (in the package) under the installed ParaView's
``pvbatch``: the volume goes
through the plugin's *Perception Measures* filter (``paraview.simple``) and ParaView renders it
with the spec's transfer functions.  The output directory receives ``screenshot.png`` (ParaView's
rendering), ``image.png`` and the three deviation maps, and ``result.json`` (``E_v``, ``E_s``,
``E_t``, per-structure values, camera).  The input options mean what they mean for ``render``
and ``measure``.

ParaView's Python must never see this environment's packages (a second VTK crashes it), so the
command builds a separate environment (:func:`paraview_env`): the repository root, the
dependency folder ``.pvdeps`` of ``make paraview-setup`` and the start-up shims of
``paraview/pvsite``.  Without a ``DISPLAY`` a private Xvfb server is started for the run
(:func:`virtual_display`; Debian's ParaView renders only through X).

``--ranks N`` runs ``mpiexec -n N pvbatch`` (the MPI that ParaView is built with; Debian's is
Open MPI, for which ``--oversubscribe`` and, as root, ``OMPI_ALLOW_RUN_AS_ROOT`` are set): each
rank reads and analyses its piece of the volume and ``result.json`` adds ``ranks``.  The ranks
read NRRD, MetaImage and VTK image files in file order (:data:`RANK_FORMATS`); a file stored
flipped, permuted or rotated, and NIfTI, DICOM, MGZ or raw files, are refused up front.
``--optimize`` runs ``paraview/batch_optimize.py`` instead (*Optimize Transfer Function*; with
``--ranks N`` over the ranks, each keeping its piece's cache entries): ``before.png``,
``after.png``, ``optimized_spec.json``, the preset and ``result.json``.  ``--timeout`` stops the
whole job (``mpiexec`` and every rank) when it takes longer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from dvr_perception import _paraview_compat, _resources
from dvr_perception._files import output_folder
from dvr_perception.cli._common import PROG, add_input_args, emit_json, log, parse_size
from dvr_perception.cli.xdisplay import display_answers, virtual_display
from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import parse_patient_view

__all__ = [
    "add_parser",
    "find_paraview",
    "mpi_command",
    "paraview_env",
    "rank_threads",
    "run",
    "run_job",
    "virtual_display",
]

#: Most ``--ranks`` (each rank is a pvbatch process holding its piece of the volume).
MAX_RANKS = 64
#: Largest ``--sigma`` (in units of the smallest voxel spacing; the Gaussian kernels reach
#: about four sigma, and a brick's ghost as far).
MAX_SIGMA = 32.0
#: Seconds a pvbatch run (all its MPI ranks) may take before it is killed (``--timeout``).
DEFAULT_TIMEOUT = 3600.0
#: Environment variable naming the directory that holds ``pvpython``/``pvbatch``.
PARAVIEW_ENV = "DVR_PERCEPTION_PARAVIEW"
#: Variables of this environment that must not reach ParaView's Python.
_DROP = ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "VTK_DEFAULT_OPENGL_WINDOW", "PV_PLUGIN_PATH")

EXAMPLE = """examples:
  dvr-perception pvbatch ../shared/data/neghip.nhdr --size 256 --out neghip_pv
  dvr-perception pvbatch ../shared/data/engine.nhdr --view=30,20 --json --out engine_pv
  dvr-perception pvbatch ../shared/data/fuel.nhdr --ranks 2 --size 128 --out fuel_mpi
"""


def add_parser(subparsers, parents) -> None:
    """Register ``pvbatch``."""
    p = subparsers.add_parser(
        "pvbatch",
        parents=parents,
        help="measure E_v, E_s, E_t inside ParaView (pvbatch) and save its rendering",
        description=__doc__.split("\n\n")[1],
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_args(p, save_spec=False)
    p.add_argument(
        "--sigma",
        type=float,
        default=1.0,
        help=f"curvature scale in voxels (default 1, at most {MAX_SIGMA:g})",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--ranks",
        type=int,
        default=1,
        metavar="N",
        help="run on N MPI ranks (mpiexec -n N pvbatch), each reading its piece (default 1, at "
        f"most {MAX_RANKS})",
    )
    p.add_argument(
        "--no-screenshot",
        action="store_true",
        help="skip ParaView's own rendering (screenshot.png; with --optimize before/after.png)",
    )
    o = p.add_argument_group(
        "optimisation (--optimize)",
        "optimise the transfer function inside ParaView (paraview/batch_optimize.py): the options "
        "mean what they mean for 'dvr-perception optimize'",
    )
    o.add_argument(
        "--optimize",
        action="store_true",
        help="run Optimize Transfer Function instead of Perception Measures; writes before.png, "
        "after.png, optimized_spec.json, the preset and result.json (with --ranks N: over the "
        "ranks, each holding its piece)",
    )
    o.add_argument("--stages", default="opacity,lighting,colour", metavar="S1,S2,..",
                   help="stages in order (default opacity,lighting,colour)")  # fmt: skip
    o.add_argument("--weights", default="1,1,1", metavar="V,S,T",
                   help="w_v,w_s,w_t >= 0 (default 1,1,1)")  # fmt: skip
    o.add_argument("--seed", type=int, default=0, metavar="N", help="annealing seed (0)")
    o.add_argument("--max-iter", type=int, default=10, metavar="N",
                   help="iterations per stage (default 10)")  # fmt: skip
    o.add_argument("--resolution", type=int, default=None, metavar="N",
                   help="long side of the optimisation camera in pixels (default 96)")  # fmt: skip
    o.add_argument("--region", metavar="X0,Y0,X1,Y1",
                   help="optimise for this image rectangle (pixels, y down)")  # fmt: skip
    p.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT,
        metavar="SECONDS",
        help=f"stop the ParaView job (every MPI rank) after this long and fail (default "
        f"{DEFAULT_TIMEOUT:g})",
    )
    p.set_defaults(run=run)


def find_paraview(program: str = "pvbatch") -> Path:
    """Return the ParaView executable ``program`` (``$DVR_PERCEPTION_PARAVIEW`` or ``PATH``).

    Raises :class:`~dvr_perception.errors.DVRInputError` when it is not installed.
    """
    folder = os.environ.get(PARAVIEW_ENV, "").strip()
    found = shutil.which(program, path=folder) if folder else shutil.which(program)
    if found is None:
        where = f"in {PARAVIEW_ENV}={folder}" if folder else "on PATH"
        raise DVRInputError(
            f"ParaView is not installed ({program} not found {where}); install it with "
            "'make paraview-setup' (as root) or 'apt-get install paraview python3-paraview xvfb'"
        )
    return Path(found)


def paraview_env(display: str | None = None, base: dict | None = None) -> dict:
    """Return the environment for ParaView's Python with the core and its dependencies.

    ``PYTHONPATH`` is ``dvr_perception/paraview/pvsite`` (start-up shims), the repository
    root (a checkout only: an installed package's ``site-packages`` holds the pip environment's
    VTK, and the start-up hook imports the package from its own folder instead) and the
    dependency folder; variables of this environment that would leak into ParaView are
    dropped.  Raises :class:`~dvr_perception.errors.DVRInputError` when the dependency
    folder is missing or unusable.
    """
    root = _paraview_compat.repo_root()
    deps = _paraview_compat.pvdeps_dir(root)
    why = _paraview_compat.check_pvdeps(deps)
    if why:
        raise DVRInputError(f"ParaView dependencies: {why}")
    site = _resources.pvsite_dir()
    if not (site / "sitecustomize.py").is_file():
        raise DVRInputError(f"{site}: not found; the package is incomplete (reinstall it)")
    env = {k: v for k, v in (os.environ if base is None else base).items() if k not in _DROP}
    path = (site, root, deps) if _paraview_compat.safe_on_path(root) else (site, deps)
    env["PYTHONPATH"] = os.pathsep.join(str(p) for p in path)
    env[_paraview_compat.PVDEPS_ENV] = str(deps)
    if display is not None:
        env["DISPLAY"] = display
    return env


def mpi_command(ranks: int, pvbatch: Path, env: dict) -> list[str]:
    """Return the ``mpiexec`` prefix for ``ranks`` ranks of ``pvbatch`` (``env`` is adjusted).

    ``mpiexec`` is looked for beside ``pvbatch``, then on ``PATH``.  Open MPI (Debian's) gets
    ``--oversubscribe`` (more ranks than cores), ``OMPI_MCA_mpi_yield_when_idle=1`` (a rank
    waiting for its turn in the view order yields the core instead of spinning) and, as root,
    ``OMPI_ALLOW_RUN_AS_ROOT``.
    """
    mpiexec = shutil.which("mpiexec", path=str(pvbatch.parent)) or shutil.which("mpiexec")
    if mpiexec is None:
        raise DVRInputError(
            "--ranks: mpiexec not found (install the MPI ParaView is built with, e.g. "
            "'apt-get install openmpi-bin')"
        )
    version = subprocess.run(
        [mpiexec, "--version"], capture_output=True, text=True, check=False
    ).stdout
    extra = []
    if "Open MPI" in version or "OpenRTE" in version:
        extra.append("--oversubscribe")
        env.setdefault("OMPI_MCA_mpi_yield_when_idle", "1")
        # the shared-memory transport's single copy (CMA) needs ptrace rights that containers
        # often lack; the copy through the shared segment always works
        env.setdefault("OMPI_MCA_btl_vader_single_copy_mechanism", "none")
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    threads = str(rank_threads(ranks))
    for name in THREAD_VARIABLES:
        env.setdefault(name, threads)
    return [mpiexec, "-n", str(int(ranks)), *extra]


#: Thread pools of each rank (numba's, OpenMP's, the BLAS'), sized by :func:`rank_threads`.
THREAD_VARIABLES = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                    "MKL_NUM_THREADS")  # fmt: skip


def rank_threads(ranks: int, cores: int | None = None) -> int:
    """Threads per rank so that ``ranks`` ranks together use the cores, not more.

    Every rank would otherwise start one numba/OpenMP/BLAS thread per core: 4 ranks on 2
    cores run 8 compute threads that take turns on the cores.

    Examples
    --------
    >>> rank_threads(4, cores=2), rank_threads(2, cores=8), rank_threads(3, cores=8)
    (1, 4, 2)
    """
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):  # not Linux
            cores = os.cpu_count() or 1
    return max(1, int(cores) // max(1, int(ranks)))


def _script_args(args: argparse.Namespace) -> list[str]:
    """Return the command line of ``paraview/batch_measure.py`` (or ``batch_optimize.py``)."""
    argv = [str(args.volume)]
    for opt in ("structures", "preset", "classes", "camera", "size", "series", "orientation"):
        if getattr(args, opt, None) is not None:
            argv += [f"--{opt}", str(getattr(args, opt))]
    if args.view is not None:
        argv.append(f"--view={args.view}")
    if args.shade is not None:
        argv.append("--shade" if args.shade else "--no-shade")
    if getattr(args, "optimize", False):
        argv += ["--stages", ",".join(args.stages), "--weights", ",".join(map(repr, args.weights)),
                 "--seed", str(args.seed), "--max-iter", str(args.max_iter),
                 "--resolution", str(args.resolution or 0)]  # fmt: skip
        if args.region:
            argv.append(f"--region={args.region}")
    else:
        argv += ["--sigma", repr(float(args.sigma))]
    argv += ["--out", str(args.out)]
    if getattr(args, "no_screenshot", False):
        argv.append("--no-screenshot")
    ranks = getattr(args, "ranks", 1)
    return [*argv, "--ranks", str(ranks)] if ranks != 1 else argv


def _check_optimize(args: argparse.Namespace) -> None:
    """Parse the optimiser's options in place (one error naming the option)."""
    from dvr_perception.cli.optimize import _numbers, parse_stages, parse_weights

    args.stages = parse_stages(args.stages)
    args.weights = parse_weights(args.weights)
    if args.seed < 0:
        raise DVRInputError(f"--seed: expected an integer >= 0, got {args.seed}")
    from dvr_perception.cli.optimize import MAX_ITER, MAX_RESOLUTION

    if not 1 <= args.max_iter <= MAX_ITER:
        raise DVRInputError(f"--max-iter: expected 1 to {MAX_ITER}, got {args.max_iter}")
    if args.resolution is not None and not 8 <= args.resolution <= MAX_RESOLUTION:
        raise DVRInputError(f"--resolution: expected 8 to {MAX_RESOLUTION}, got {args.resolution}")
    if args.region is not None:
        _numbers(args.region, "--region", 4, "four numbers x0,y0,x1,y1")


def _failure(returncode: int, stderr: str) -> Exception:
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    prefix = f"{PROG}: error: "
    mine = [ln[len(prefix) :] for ln in lines if ln.startswith(prefix)]
    if mine and returncode == 2:
        return DVRInputError(mine[-1])
    if mine:
        return RuntimeError(f"pvbatch failed with exit code {returncode}: {mine[-1]}")
    # ParaView's own errors (loguru "ERR|" lines) say more than mpiexec's closing banner
    lines = [re.sub(r"\x1b\[[0-9;]*m", "", ln).strip() for ln in lines]
    lines = [ln for ln in lines if ln.strip("-") and not ln.startswith("[")] or lines
    errs = [ln for ln in lines if "ERR|" in ln]
    lines = errs or lines
    last = lines[-1] if lines else "no output"
    return RuntimeError(f"pvbatch failed with exit code {returncode}: {last} (rerun with -v)")


def _warm_up(pvbatch: Path, env: dict, *, optimize: bool = False) -> None:
    """Compile the ranks' kernels in one pvbatch process first (``distributed.warm_up``)."""
    import tempfile

    log.info("compiling the ranks' kernels once (seconds when cached)")
    with tempfile.TemporaryDirectory(prefix="dvr-warm-") as tmp:
        script = Path(tmp) / "warm_up.py"
        script.write_text(
            f"from dvr_perception.distributed import warm_up\nwarm_up(optimize={optimize})\n",
            encoding="utf-8",
        )
        for _ in (1, 2):  # Debian's pvbatch may abort at start-up: one retry
            proc = subprocess.run(
                [str(pvbatch), str(script)], env=env, capture_output=True, text=True, check=False
            )
            if proc.returncode >= 0:
                break
    if proc.returncode != 0:  # only a head start: the ranks compile what is missing
        log.warning("compiling the ranks' kernels first failed (exit %d); going on",
                    proc.returncode)  # fmt: skip


def run_job(cmd: list[str], env: dict, timeout: float, what: str) -> subprocess.CompletedProcess:
    """Run ``cmd`` (``pvbatch`` or ``mpiexec ... pvbatch``) in its own process group.

    After ``timeout`` seconds the whole group (``mpiexec`` and every rank) gets SIGTERM, then
    SIGKILL, and a ``RuntimeError`` names ``what`` and ``--timeout``: a rank that hangs never
    leaves the command (or a test) waiting.  Interrupted (Ctrl-C, or SIGTERM raised by the
    command line), the group is killed before the interrupt goes on: being in a session of its
    own it would otherwise keep running.
    """
    import signal

    proc = subprocess.Popen(
        cmd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, None)):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.communicate(timeout=wait)
                break
            except subprocess.TimeoutExpired:
                continue
        proc.wait()
        raise RuntimeError(
            f"{what} did not finish within {timeout:g} s (--timeout); the job was killed"
        ) from None
    except BaseException:  # Ctrl-C or SIGTERM: the job's own session would outlive us
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        for pipe in (proc.stdout, proc.stderr):
            pipe.close()
        proc.wait()
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def _launch(args: argparse.Namespace, pvbatch: Path) -> subprocess.CompletedProcess:
    """Run the batch script under ``pvbatch`` (retrying ParaView's start-up crashes)."""
    name = "batch_optimize.py" if args.optimize else "batch_measure.py"
    script = _resources.paraview_dir() / name
    env = paraview_env()
    prefix = mpi_command(args.ranks, pvbatch, env) if args.ranks > 1 else []
    if prefix:
        _warm_up(pvbatch, env, optimize=args.optimize)
    for attempt in (1, 2, 3):
        with virtual_display() as display:
            env["DISPLAY"] = display
            what = f"pvbatch{f' --ranks {args.ranks}' if args.ranks > 1 else ''}"
            proc = run_job(
                [*prefix, str(pvbatch), str(script), *_script_args(args)],
                env,
                args.timeout,
                what,
            )
            x_abort = "bad X server connection" in (proc.stderr or "")
            if x_abort:  # which of the two failed: the server, or ParaView's client
                answers = display_answers(display)
                log.warning("ParaView could not open display %s; the display %s a new client",
                            display, "answers" if answers else "does not answer")  # fmt: skip
        # a signal (negative code; under mpiexec 128 + signal and ParaView's X message) is
        # ParaView crashing, not our script's error.  "bad X server connection" was mostly Xvfb
        # resetting after a client left (now -noreset, see xdisplay); two retries on a fresh
        # display remain as a safety net, then the crash is reported
        crashed = proc.returncode < 0 or x_abort
        if not crashed or attempt == 3:
            break
        log.warning("pvbatch crashed (exit %d); retrying on a new display", proc.returncode)
    if args.verbose and proc.stderr:
        sys.stderr.write(proc.stderr)
    if proc.returncode != 0:
        raise _failure(proc.returncode, proc.stderr)
    return proc


#: What the MPI ranks can read: ParaView's readers of these formats, in file order; NRRD,
#: MetaImage and ``.vti`` axes are checked from the header, legacy ``.vtk`` records none.
RANK_FORMATS = (".nhdr", ".nrrd", ".mha", ".mhd", ".vti", ".vtk")


def _check_file_order(volume: str) -> None:
    """Refuse ``--ranks N`` for a file whose axes are not the patient axes in LPS order.

    The ranks read their pieces with ParaView's readers, in file order; a flipped, permuted or
    rotated file would be measured mirrored or turned (``--ranks 1`` reads it in patient LPS).
    Formats whose orientation only our readers apply -- NIfTI's s-form/q-form, DICOM's
    position and orientation, the ``.mgz`` affine -- and headerless raw are refused.
    """
    from dvr_perception.volume.io import _ext, header_axes

    path = Path(volume)
    if not path.exists():
        return  # the run reports a missing file itself
    ext = "" if path.is_dir() else _ext(path)
    if ext not in RANK_FORMATS:
        kind = "a DICOM folder" if path.is_dir() else f"a {ext or 'extensionless'} file"
        raise DVRInputError(
            f"--ranks: {volume} is {kind}; the MPI ranks read only NRRD, MetaImage and VTK "
            "image files (with ParaView's readers, in file order, which would drop the "
            "orientation of NIfTI, DICOM and MGZ files): run with --ranks 1 (read in patient "
            "LPS), or re-save it as .nrrd first"
        )
    axes = header_axes(volume)
    if axes is None:
        return
    if np.count_nonzero(axes - np.diag(np.diag(axes))) or np.any(np.diag(axes) <= 0):
        vectors = " ".join(f"({','.join(f'{v:g}' for v in col)})" for col in axes.T)
        raise DVRInputError(
            f"--ranks: {volume} stores its axes flipped, permuted or rotated (axis vectors "
            f"{vectors} in LPS); the MPI ranks read the file as it is stored, which would "
            "measure it mirrored or turned: run with --ranks 1 (read in patient LPS), or "
            "re-save it in LPS order first"
        )


def run(args: argparse.Namespace) -> int:
    """Execute ``pvbatch``."""
    if not 1 <= args.ranks <= MAX_RANKS:
        raise DVRInputError(f"--ranks: expected 1 to {MAX_RANKS} ranks, got {args.ranks}")
    if args.size is not None:
        parse_size(args.size)
    if args.view is not None:
        name, *_ = parse_patient_view(args.view)
        if name is not None and getattr(args, "ranks", 1) > 1:
            raise DVRInputError(
                f"--view {args.view}: a named patient view needs --ranks 1 (the MPI path "
                "takes A,E[,Z])"
            )
    if getattr(args, "orientation", None) is not None and getattr(args, "ranks", 1) > 1:
        raise DVRInputError(
            "--orientation: needs --ranks 1 (the MPI ranks read the file as it is stored)"
        )
    if getattr(args, "ranks", 1) > 1:
        _check_file_order(args.volume)
    if not (0 < args.sigma <= MAX_SIGMA):
        raise DVRInputError(
            f"--sigma: expected a positive number of at most {MAX_SIGMA:g}, got {args.sigma}"
        )
    if not (0 < args.timeout < math.inf):
        raise DVRInputError(f"--timeout: expected a positive number of seconds, got {args.timeout}")
    if args.optimize:
        _check_optimize(args)
    pvbatch = find_paraview("pvbatch")
    # ParaView writes into a staging folder inside --out, locked against a second run; the
    # files move in together only when the job succeeded (an interrupted or failed run leaves
    # the folder as it was)
    with output_folder(args.out) as staged:
        job = argparse.Namespace(**vars(args))
        job.out = staged.path
        proc = _launch(job, pvbatch)
        summary = json.loads(proc.stdout.strip().splitlines()[-1])
        result_json = (staged.path / "result.json").read_text(encoding="utf-8")
    summary["out"] = str(staged.final)
    mpi = f", {args.ranks} MPI ranks" if args.ranks > 1 else ""
    if args.json:
        emit_json(json.loads(result_json))
    elif args.optimize:
        print(
            f"E {summary['initial_E']:.4f} -> {summary['E']:.4f}  (ParaView pvbatch{mpi}; "
            f"before.png, after.png, optimized_spec.json and result.json in {summary['out']})"
        )
    else:
        print(
            f"E_v = {summary['E_v']:.4f}  E_s = {summary['E_s']:.4f}  E_t = {summary['E_t']:.4f}"
            f"  (ParaView pvbatch{f', {args.ranks} MPI ranks' if args.ranks > 1 else ''};"
            f" images and result.json in {summary['out']})"
        )
    return 0
