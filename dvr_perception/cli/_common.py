"""Options and helpers shared by the ``dvr-perception`` sub-commands.

A *scene* is what every command starts from: a volume, its structure spec and a camera.
:func:`add_scene_args` declares the options that choose them and :func:`load_scene` resolves
them with the documented defaults (the spec paired with the volume, the spec's view, 512²).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

import dvr_perception
from dvr_perception._files import json_ready, write_npz
from dvr_perception.errors import DVRInputError
from dvr_perception.rays.camera import Camera, parse_view

__all__ = [
    "PROG",
    "CLIParser",
    "Scene",
    "add_scene_args",
    "check_output_file",
    "common_parent",
    "emit_json",
    "load_scene",
    "parse_factors",
    "parse_size",
    "save_buffers",
]

PROG = "dvr-perception"
DEFAULT_SIZE = 512
log = logging.getLogger("dvr_perception.cli")


class CLIParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose usage errors are one-line DVRInputErrors."""

    def error(self, message):
        raise DVRInputError(f"{message} (see '{self.prog} --help')")


def common_parent() -> argparse.ArgumentParser:
    """Options every sub-command accepts: ``--json``, ``--debug``, ``-v``."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument(
        "--json", action="store_true", help="print exactly one JSON object on stdout"
    )
    parent.add_argument(
        "--debug", action="store_true", help="show tracebacks for unexpected errors"
    )
    parent.add_argument("-v", "--verbose", action="store_true", help="log progress on stderr")
    return parent


def add_scene_args(parser: argparse.ArgumentParser, *, volume_optional: bool = False) -> None:
    """Declare VOLUME, ``--structures``, ``--view``/``--camera``, ``--size``, ``--shade``."""
    help_volume = "volume file (.nhdr, .nrrd, .mha, .vti, ...) or the word 'phantom'"
    if volume_optional:
        parser.add_argument(
            "volume", nargs="?", default="phantom", metavar="VOLUME", help=help_volume
        )
    else:
        parser.add_argument("volume", metavar="VOLUME", help=help_volume)
    parser.add_argument(
        "--structures",
        metavar="SPEC.json",
        help="structure spec (default: the spec paired with the volume, else a proposal)",
    )
    cam = parser.add_mutually_exclusive_group()
    cam.add_argument(
        "--view",
        metavar="A,E[,Z]",
        help="azimuth, elevation (degrees) and zoom; use --view=-30,10 for negative angles",
    )
    cam.add_argument("--camera", metavar="CAM.json", help="camera JSON (Camera.to_dict format)")
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
        help="memory the analysis may use, e.g. 8G or 512M (default: half the machine's "
        "memory); larger volumes are analysed in bricks, and a run that cannot fit stops "
        "before it starts",
    )


_SIZE = re.compile(r"^\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*$")


def parse_size(text) -> tuple[int, int]:
    """Parse ``--size``: ``"N"`` (square) or ``"WxH"``, each between 1 and 16384.

    Examples
    --------
    >>> parse_size("64"), parse_size("320x200")
    ((64, 64), (320, 200))
    """
    m = _SIZE.match(str(text))
    if m is None:
        raise DVRInputError(f"--size: expected N or WxH (positive integers), got {text!r}")
    w = int(m.group(1))
    h = int(m.group(2)) if m.group(2) is not None else w
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise DVRInputError(f"--size: width and height must be in 1..16384, got {text!r}")
    return w, h


_FACTORS = re.compile(r"^\s*(\d+)\s*(?:,\s*(\d+)\s*,\s*(\d+)\s*)?$")


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
            f"--resample: expected F or FX,FY,FZ (positive integers along x, y, z), got {text!r}"
        )
    f = tuple(int(g) for g in m.groups()) if m.group(2) is not None else (int(m.group(1)),) * 3
    if not all(1 <= k <= 64 for k in f):
        raise DVRInputError(f"--resample: factors must be in 1..64, got {text!r}")
    return f  # type: ignore[return-value]


@dataclass
class Scene:
    """A resolved volume, spec and camera, with where they came from."""

    volume: object
    spec: object
    camera: Camera
    volume_source: str
    spec_source: str
    load_s: float


def state_files_dir() -> Path:
    """Return the repository's ``state_files`` folder (specs paired with shared volumes)."""
    return Path(dvr_perception.__file__).resolve().parents[1] / "state_files"


def _load_volume(text: str, *, paired: bool = True):
    """Return ``(volume, paired_spec_or_None, paired_source)`` for a VOLUME argument."""
    if text == "phantom":
        from dvr_perception.volume.phantom import make_phantom

        volume, spec = make_phantom()
        return volume, spec, "phantom (built-in spec)"
    from dvr_perception.volume.io import load_volume

    path = Path(text)
    volume = load_volume(path)
    spec_file = state_files_dir() / f"{path.name.split('.')[0]}.json"
    if paired and spec_file.is_file():
        from dvr_perception.structures.io import load_spec

        return volume, load_spec(spec_file), str(spec_file)
    return volume, None, ""


def _read_camera(path_text: str, size: tuple[int, int] | None) -> Camera:
    path = Path(path_text)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DVRInputError(f"--camera {path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DVRInputError(f"--camera {path}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise DVRInputError(
            f"--camera {path}: not valid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    cam = Camera.from_dict(d, source=f"--camera {path}")
    return cam.with_size(*size) if size is not None else cam


def load_scene(args: argparse.Namespace) -> Scene:
    """Resolve the scene options of :func:`add_scene_args` into a :class:`Scene`.

    Cheap checks (size, view, camera file) run before the volume is loaded, so bad options
    fail fast.  A command that declares ``--resample`` gets the volume (and labels) up-sampled
    (:func:`dvr_perception.volume.resample.upsample`) before the camera is fitted to it.
    """
    size = parse_size(args.size) if args.size is not None else None
    if getattr(args, "memory_limit", None) is not None:
        from dvr_perception.rays import memory

        memory.set_limit(args.memory_limit)  # checked here, before the volume is read
        os.environ[memory.ENV] = str(args.memory_limit)  # and for child processes
    resample = getattr(args, "resample", None)  # only commands that declare --resample
    factors = parse_factors(resample) if resample is not None else None
    view = parse_view(args.view) if args.view is not None else None
    camera = _read_camera(args.camera, size) if args.camera is not None else None
    from dvr_perception.structures.io import attach_labels, check_spec_for_volume, load_spec

    given = load_spec(args.structures) if args.structures is not None else None
    t0 = time.perf_counter()
    log.info("loading volume %s", args.volume)
    volume, spec, spec_source = _load_volume(args.volume, paired=given is None)
    load_s = time.perf_counter() - t0
    if given is not None:
        spec, spec_source = given, str(args.structures)
    elif spec is None:
        from dvr_perception.structures.propose import propose_structures

        log.info("no spec given or paired with %s: proposing structures", args.volume)
        spec, spec_source = propose_structures(volume), "proposed"
    volume = attach_labels(volume, spec)
    if factors is not None and factors != (1, 1, 1):
        from dvr_perception.volume.resample import upsample

        log.info("up-sampling by %s (x, y, z)", factors)
        t0 = time.perf_counter()
        volume = upsample(volume, factors)
        load_s += time.perf_counter() - t0
    check_spec_for_volume(spec, volume)
    if args.shade is not None:
        spec = replace(spec, rendering=replace(spec.rendering, shade=bool(args.shade)))
    if camera is None:
        az, el, zoom = view if view is not None else (spec.view or (0.0, 0.0, 1.0))
        w, h = size if size is not None else (DEFAULT_SIZE, DEFAULT_SIZE)
        camera = Camera.from_view(
            volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=w, height=h
        )
    return Scene(volume, spec, camera, args.volume, spec_source, load_s)


def check_output_file(path) -> Path:
    """Fail early (before any rendering) when an output file cannot be created."""
    p = Path(path)
    if p.is_dir():
        raise DVRInputError(f"output file {p}: is a directory; expected a file name")
    if not p.parent.is_dir():
        raise DVRInputError(f"output file {p}: directory {p.parent} does not exist")
    return p


def make_output_dir(path) -> Path:
    """Create an output directory (and parents) if needed."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise DVRInputError(f"output directory {p}: exists and is not a directory")
    p.mkdir(parents=True, exist_ok=True)
    return p


def save_buffers(path, result) -> Path:
    """Write the per-pixel buffers of a ray analysis to an ``.npz`` file (atomically)."""
    return write_npz(
        path,
        rgba=result.rgba,
        image=result.image,
        accumulated=result.accumulated,
        visible=result.visible,
        assigned=result.assigned,
        visible_share=result.visible_share,
        assigned_share=result.assigned_share,
        present=result.present,
        curvature=result.curvature,
        names=np.array(list(result.names), dtype=str),
        camera=np.array(json.dumps(result.camera.to_dict())),
    )


def coverage(result) -> float:
    """Fraction of pixels with any accumulated opacity."""
    return float(np.mean(np.asarray(result.accumulated) > 0))


def emit_json(obj) -> None:
    """Print ``obj`` as exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(json_ready(obj)) + "\n")
    sys.stdout.flush()
