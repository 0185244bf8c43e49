"""What every front end starts from: a volume, its structure spec and a camera.

The command line (``dvr-perception measure/optimize/render/...``), the ParaView plugin's batch
scripts (``dvr-perception pvbatch``) and the web app load their inputs through this module:

* :func:`add_input_args` declares the options that choose them (VOLUME, ``--structures`` /
  ``--preset`` / ``--classes``, ``--view`` / ``--camera``, ``--size``, ``--shade``,
  ``--memory-limit``, ...) on an :class:`argparse.ArgumentParser` (an :class:`OptionParser`
  turns usage errors into one-line :class:`~dvr_perception.errors.DVRInputError`);
* :func:`load_inputs` resolves them with the documented defaults (the preset paired with the
  volume by its data checksum, else a proposal; the spec's view; 512²) into
  :class:`RenderInputs`;
* :func:`load_volume_and_spec` is the volume-plus-paired-spec step alone (the phantom, or a
  file with :func:`~dvr_perception.structures.presets.choose_spec`).

The presets themselves are :mod:`dvr_perception.structures.presets`.  This module sits above the
optimiser in the layering (it is used only by front ends).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import stat
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.rays.camera import (
    MAX_IMAGE,
    Camera,
    default_camera,
    parse_patient_view,
    patient_view,
)

__all__ = [
    "DEFAULT_SIZE",
    "MAX_JSON_BYTES",
    "ORIENTATION_HELP",
    "OptionParser",
    "RenderInputs",
    "add_input_args",
    "check_output_file",
    "check_resample",
    "load_inputs",
    "load_volume_and_spec",
    "make_output_dir",
    "parse_factors",
    "parse_rect",
    "parse_size",
    "read_camera",
    "read_json_file",
]

#: Image size (pixels, square) when neither ``--size`` nor ``--camera`` gives one.
DEFAULT_SIZE = 512
log = logging.getLogger("dvr_perception.inputs")


class OptionParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose usage errors are one-line DVRInputErrors."""

    def error(self, message):
        """Raise the usage error ``message`` as a DVRInputError pointing to ``--help``."""
        raise DVRInputError(f"{message} (see '{self.prog} --help')")


#: Help of ``--orientation`` (every command that reads a volume, and ``app``).
ORIENTATION_HELP = (
    "where the volume's index axes x, y, z point, for a file that records no orientation: "
    "three letters from L/R, P/A, S/I (e.g. LPI: slice 0 is the top of the head); the data "
    "are re-ordered into patient LPS (default: as the file says, else LPS)"
)


def add_input_args(
    parser: argparse.ArgumentParser, *, volume_optional: bool = False, save_spec: bool = True
) -> None:
    """Declare VOLUME, ``--structures``, ``--view``/``--camera``, ``--size``, ``--shade``.

    With ``save_spec`` also ``--save-spec`` (written by :func:`load_inputs`).
    """
    help_volume = "volume file (.nhdr, .nrrd, .mha, .vti, ...) or the word 'phantom'"
    if volume_optional:
        parser.add_argument(
            "volume", nargs="?", default="phantom", metavar="VOLUME", help=help_volume
        )
    else:
        parser.add_argument("volume", metavar="VOLUME", help=help_volume)
    spec_group = parser.add_mutually_exclusive_group()
    spec_group.add_argument(
        "--structures",
        metavar="SPEC.json",
        help="structure spec, or a 3D Slicer segmentation (.seg.nrrd: one label structure per "
        "segment) (default: the preset whose recorded data checksum matches the volume's, else "
        "a proposal)",
    )
    spec_group.add_argument(
        "--preset",
        metavar="NAME",
        help="use the preset NAME of the repository's state_files/ (e.g. cthead) whatever the data",
    )
    spec_group.add_argument(
        "--classes",
        metavar="N",
        type=_classes,
        help="propose structures from the data even when a preset matches: 'auto' (the number "
        "the data choose) or N (1 to 8)",
    )
    if save_spec:
        parser.add_argument(
            "--save-spec",
            metavar="OUT.json",
            help="also write the structure spec used (e.g. the one made from a .seg.nrrd or "
            "proposed) as an editable spec JSON",
        )
    cam = parser.add_mutually_exclusive_group()
    cam.add_argument(
        "--view",
        metavar="[NAME,]A,E[,Z]",
        help="azimuth, elevation (degrees) and zoom, relative to the down -z, +y up view or to a "
        "patient view NAME: anterior, posterior, left, right, superior, inferior (patient LPS, "
        "e.g. --view anterior shows the face); use --view=-30,10 for negative angles (default: "
        "the spec's view, else anterior for a scan that records its orientation, else down -z)",
    )
    cam.add_argument("--camera", metavar="CAM.json", help="camera JSON (Camera.to_dict format)")
    parser.add_argument("--orientation", metavar="CODE", help=ORIENTATION_HELP)
    parser.add_argument(
        "--series",
        metavar="UID",
        help="DICOM folder holding several series: the SeriesInstanceUID to read (without it, "
        "such a folder is refused with the list of its series)",
    )
    parser.add_argument(
        "--size", metavar="N|WxH", help=f"image size in pixels (default {DEFAULT_SIZE})"
    )
    parser.add_argument(
        "--shade",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="Phong shading on/off (default: the spec's rendering.shade)",
    )
    parser.add_argument(
        "--memory-limit",
        metavar="SIZE",
        help="memory the analysis may use, e.g. 8G or 512M (default: a quarter of the "
        "machine's memory); larger volumes are analysed in bricks, and a run that cannot "
        "fit stops before it starts",
    )
    parser.add_argument(
        "--allow-data-root",
        metavar="DIR",
        action="append",
        help="also accept a volume header's detached data file inside DIR (default: only "
        "inside the header's own folder); repeatable",
    )


_SIZE = re.compile(r"^\s*(\d{1,9})\s*(?:[xX]\s*(\d{1,9}))?\s*$")
#: Largest camera or spec JSON file read (bytes).
MAX_JSON_BYTES = 16 * 2**20


def parse_size(text) -> tuple[int, int]:
    """Parse ``--size``: ``"N"`` (square) or ``"WxH"``, each between 1 and 16384.

    Examples
    --------
    >>> parse_size("64"), parse_size("320x200")
    ((64, 64), (320, 200))
    """
    m = _SIZE.match(str(text))
    if m is None:
        raise DVRInputError(f"--size: expected N or WxH (positive integers), got {_cut(text)}")
    w = int(m.group(1))
    h = int(m.group(2)) if m.group(2) is not None else w
    if not (1 <= w <= MAX_IMAGE and 1 <= h <= MAX_IMAGE):
        raise DVRInputError(f"--size: width and height must be in 1..{MAX_IMAGE}, got {text!r}")
    return w, h


def _cut(text, limit: int = 40) -> str:
    text = str(text)
    return repr(text) if len(text) <= limit else f"{text[:30]!r}... ({len(text)} characters)"


def read_json_file(path, what: str):
    """Read a small JSON file (a regular file of at most :data:`MAX_JSON_BYTES`).

    ``what`` starts every error message (e.g. ``"--camera cam.json"``).  Devices, FIFOs and
    folders are refused before anything is read.
    """
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise DVRInputError(f"{what}: file not found") from None
    except OSError as exc:
        raise DVRInputError(f"{what}: cannot read ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise DVRInputError(f"{what}: not a regular file")
    if st.st_size > MAX_JSON_BYTES:
        raise DVRInputError(
            f"{what}: the file has {st.st_size} bytes, more than the {MAX_JSON_BYTES} allowed"
        )
    try:
        with open(p, encoding="utf-8") as fh:
            text = fh.read(MAX_JSON_BYTES + 1)
    except (OSError, UnicodeDecodeError) as exc:
        raise DVRInputError(f"{what}: cannot read ({exc})") from None
    from dvr_perception.structures.io import loads_json

    return loads_json(text, what)


_FACTORS = re.compile(r"^\s*(\d{1,9})\s*(?:,\s*(\d{1,9})\s*,\s*(\d{1,9})\s*)?$")


def parse_factors(text) -> tuple[int, int, int]:
    """Parse ``--resample``: ``"F"`` (all axes) or ``"FX,FY,FZ"``, each between 1 and 64.

    Examples
    --------
    >>> parse_factors("2,2,4"), parse_factors("3")
    ((2, 2, 4), (3, 3, 3))
    """
    m = _FACTORS.match(str(text))
    if m is None:
        raise DVRInputError(
            f"--resample: expected F or FX,FY,FZ (positive integers along x, y, z), got "
            f"{_cut(text)}"
        )
    f = tuple(int(g) for g in m.groups()) if m.group(2) is not None else (int(m.group(1)),) * 3
    if not all(1 <= k <= 64 for k in f):
        raise DVRInputError(f"--resample: factors must be in 1..64, got {text!r}")
    return f  # type: ignore[return-value]


def check_resample(volume, factors, text=None) -> None:
    """Refuse ``--resample`` factors whose up-sampled volume exceeds the memory limit.

    Counted before anything is allocated: the up-sampled voxels (and labels) next to the
    volume itself, against :func:`dvr_perception._memory.limit` (``--memory-limit``).

    Examples
    --------
    >>> from dvr_perception.volume import Volume
    >>> vol = Volume(np.zeros((64, 64, 64), np.uint16))
    >>> check_resample(vol, (2, 2, 2), "2")  # 4 MiB
    >>> check_resample(vol, (64, 64, 64), "64")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    dvr_perception.errors.DVRInputError: --resample 64: the up-sampled volume of 4096x4096x4096 voxels needs about 128.00 GB, more than the memory limit of ... GB; use smaller factors or raise --memory-limit (or DVR_PERCEPTION_MEMORY_LIMIT)
    """  # noqa: E501
    from dvr_perception import _memory as memory

    data = volume.data
    scale = int(np.prod(factors, dtype=np.int64))
    per_voxel = data.itemsize + (volume.labels.itemsize if volume.labels is not None else 0)
    need = data.size * scale * per_voxel + data.size * per_voxel
    cap = memory.limit()
    if need > cap:
        dims = "x".join(str(n * f) for n, f in zip(data.shape[::-1], factors, strict=True))
        shown = ",".join(map(str, factors)) if text is None else str(text).strip()
        raise DVRInputError(
            f"--resample {shown}: the up-sampled volume of {dims} voxels needs about "
            f"{memory.human_bytes(need)}, more than the memory limit of "
            f"{memory.human_bytes(cap)}; use "
            f"smaller factors or raise --memory-limit (or {memory.ENV})"
        )


@dataclass
class RenderInputs:
    """A resolved volume, structure spec and camera, with where they came from.

    ``spec_line`` says, in one line, which spec was chosen and why when it was not given
    (e.g. ``"structures: preset 'cthead' (data checksum matches)"``), else ``""``.
    """

    volume: object
    spec: object
    camera: Camera
    volume_source: str
    spec_source: str
    load_s: float
    spec_line: str = ""


def _classes(text) -> int | str:
    """Parse ``--classes``: ``auto`` or an integer from 1 to 8."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        n = int(str(text))
    except ValueError:
        msg = f"expected 'auto' or an integer from 1 to 8, got {_cut(text)}"
        raise argparse.ArgumentTypeError(msg) from None
    if not 1 <= n <= 8:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer from 1 to 8, got {n}")
    return n


def load_volume_and_spec(
    text: str, *, paired: bool = True, series: str | None = None, classes=None
):
    """Return ``(volume, spec_or_None, spec_source, line)`` for a VOLUME argument.

    ``text`` is a volume file or the word ``phantom`` (the built-in phantom and its spec).

    With ``paired`` the spec is chosen by
    :func:`~dvr_perception.structures.presets.choose_spec` (a preset whose data checksum
    matches, else a proposal; ``classes`` asks for a proposal of that many structures).
    """
    if text == "phantom":
        from dvr_perception.structures.phantom import make_phantom

        volume, spec = make_phantom()
        return volume, spec, "phantom (built-in spec)", ""
    from dvr_perception.volume.io import load_volume

    path = Path(text)
    volume = load_volume(path, series=series) if series is not None else load_volume(path)
    if paired:
        from dvr_perception.structures.presets import choose_spec

        auto = classes == "auto"
        choice = choose_spec(volume, n_structures=None if auto else classes, propose=auto)
        return volume, choice.spec, choice.source, choice.line
    return volume, None, "", ""


def read_camera(path_text, size: tuple[int, int] | None = None) -> Camera:
    """Read a camera JSON file (``--camera``, :meth:`Camera.to_dict` format) at ``size``."""
    path = Path(path_text)
    d = read_json_file(path, f"--camera {path}")
    cam = Camera.from_dict(d, source=f"--camera {path}")
    return cam.with_size(*size) if size is not None else cam


def load_inputs(args: argparse.Namespace) -> RenderInputs:
    """Resolve the options of :func:`add_input_args` into :class:`RenderInputs`.

    Cheap checks (size, view, camera file) run before the volume is loaded, so bad options
    fail fast.  A command that declares ``--resample`` gets the volume (and labels) up-sampled
    (:func:`dvr_perception.volume.resample.upsample`) before the camera is fitted to it.
    """
    from dvr_perception.rays import memory

    size = parse_size(args.size) if args.size is not None else None
    if getattr(args, "memory_limit", None) is not None:
        memory.set_limit(args.memory_limit)  # checked here, before the volume is read
        os.environ[memory.ENV] = str(args.memory_limit)  # and for child processes
    if getattr(args, "allow_data_root", None):
        from dvr_perception.volume._limits import DATA_ROOTS_ENV

        for root in args.allow_data_root:
            if not Path(root).is_dir():
                raise DVRInputError(f"--allow-data-root {root}: not a folder")
        os.environ[DATA_ROOTS_ENV] = os.pathsep.join(args.allow_data_root)
    resample = getattr(args, "resample", None)  # only commands that declare --resample
    factors = parse_factors(resample) if resample is not None else None
    view = parse_patient_view(args.view) if args.view is not None else None
    if getattr(args, "orientation", None) is not None:
        from dvr_perception.volume.orient import parse_orientation

        parse_orientation(args.orientation)  # before the volume is read
    camera = read_camera(args.camera, size) if args.camera is not None else None
    save_to = getattr(args, "save_spec", None)
    if save_to is not None:
        save_to = check_output_file(save_to)
    from dvr_perception.structures.io import attach_labels, check_spec_for_volume, load_spec

    given, given_source, given_line = None, "", ""
    if args.structures is not None:  # the user's own spec: nothing to explain
        given, given_source = load_spec(args.structures), str(args.structures)
    elif getattr(args, "preset", None) is not None:
        from dvr_perception.structures.presets import load_preset

        given, path = load_preset(args.preset)
        given_source = str(path)
        given_line = f"structures: preset {args.preset!r} (given with --preset)"
    k = len(given.structures) if given is not None else 1
    if camera is not None:  # before the volume is read: the image must fit the limit
        memory.check_image(camera.width, camera.height, k, source=f"--camera {args.camera}")
    elif size is not None:
        memory.check_image(*size, k)
    t0 = time.perf_counter()
    log.info("loading volume %s", args.volume)
    volume, spec, spec_source, spec_line = load_volume_and_spec(
        args.volume,
        paired=given is None,
        series=getattr(args, "series", None),
        classes=getattr(args, "classes", None),
    )
    load_s = time.perf_counter() - t0
    if given is not None:
        spec, spec_source, spec_line = given, given_source, given_line
    volume = attach_labels(volume, spec)
    if getattr(args, "orientation", None) is not None:
        from dvr_perception.volume.orient import reorient

        volume = reorient(volume, args.orientation)
    if factors is not None and factors != (1, 1, 1):
        from dvr_perception.volume.resample import upsample

        check_resample(volume, factors, resample)
        log.info("up-sampling by %s (x, y, z)", factors)
        t0 = time.perf_counter()
        volume = upsample(volume, factors)
        load_s += time.perf_counter() - t0
    check_spec_for_volume(spec, volume)
    if args.shade is not None:
        spec = replace(spec, rendering=replace(spec.rendering, shade=bool(args.shade)))
    if save_to is not None:
        from dvr_perception.structures.io import save_spec

        save_spec(spec, save_to)
        log.info("wrote the structure spec to %s", save_to)
    if camera is None:
        w, h = size if size is not None else (DEFAULT_SIZE, DEFAULT_SIZE)
        if view is None:  # the spec's view, else anterior for an oriented scan
            camera = default_camera(volume, spec.view, width=w, height=h)
        elif view[0] is not None:
            name, az, el, zoom = view
            _warn_unoriented(volume)
            camera = patient_view(
                volume, name, azimuth=az, elevation=el, zoom=zoom, width=w, height=h
            )
        else:
            _, az, el, zoom = view
            camera = Camera.from_view(
                volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=w, height=h
            )
    return RenderInputs(volume, spec, camera, args.volume, spec_source, load_s, spec_line)


def _warn_unoriented(volume) -> None:
    """Warn (one line) that a patient view of a file without orientation is a guess.

    Silent for a file that records its orientation and after ``--orientation`` (which makes
    the volume ``oriented``).
    """
    from dvr_perception.volume.orient import orientation_note

    note = orientation_note(volume)
    if note is not None:
        warnings.warn(note, DVRWarning, stacklevel=3)


def check_output_file(path) -> Path:
    """Fail early (before any rendering) when an output file cannot be created.

    The folder must exist and be writable, and an existing target must be a regular file.
    """
    from dvr_perception._files import check_target, check_writable

    p = check_target(path)
    check_writable(p.parent)
    return p


def make_output_dir(path) -> Path:
    """Create an output directory (and parents) if needed."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise DVRInputError(f"output directory {p}: exists and is not a directory")
    p.mkdir(parents=True, exist_ok=True)
    return p


def _numbers(text, option: str, count: int, what: str) -> list[float]:
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise DVRInputError(f"{option}: expected {what}, got {_cut(text)}")
    return values


def parse_rect(text: str, width: int, height: int) -> tuple[float, float, float, float]:
    """Parse ``--region X0,Y0,X1,Y1``; check that it holds pixels of the ``width x height`` image.

    Examples
    --------
    >>> parse_rect("0,0,8.5,4", 16, 16)
    (0.0, 0.0, 8.5, 4.0)
    """
    x0, y0, x1, y1 = _numbers(text, "--region", 4, "four numbers x0,y0,x1,y1")
    if not (x0 < x1 and y0 < y1):
        raise DVRInputError(f"--region: expected x0 < x1 and y0 < y1, got {text!r}")
    cols = np.arange(width) + 0.5
    rows = np.arange(height) + 0.5
    if not (np.any((cols > x0) & (cols < x1)) and np.any((rows > y0) & (rows < y1))):
        raise DVRInputError(
            f"--region: {text!r} holds no pixel (centre) of the {width}x{height} image"
        )
    return x0, y0, x1, y1
