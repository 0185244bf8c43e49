"""``dvr-perception app``: serve the web app (:mod:`dvr_perception.app`) on the loopback address.

The app needs the ``app`` extra (``pip install 'dvr-perception[app]'``).  It listens on
127.0.0.1 by default and prints the address to open, with a random secret made for this run
(``?secret=...``); without it no page or websocket is served (see the manual's Security
page, ``docs/guide/security.md``).  It reads the data folder only and writes into a
per-user state folder (``--state-dir``).
"""

from __future__ import annotations

import os
from pathlib import Path

from dvr_perception.cli._common import ORIENTATION_HELP, log
from dvr_perception.errors import DVRInputError

__all__ = ["add_parser", "default_data_dir", "run"]


def default_data_dir() -> Path | None:
    """``$DVR_SHARED_DATA`` or ``../shared/data`` (from the working folder), if present."""
    for text in (os.environ.get("DVR_SHARED_DATA"), "../shared/data"):
        if text and Path(text).is_dir():
            return Path(text)
    return None


def add_parser(subparsers, parents) -> None:
    """Register the ``app`` sub-command."""
    p = subparsers.add_parser(
        "app",
        parents=parents,
        help="serve the interactive web app (needs the 'app' extra)",
        description="Serve the web app: choose a volume, edit structures, see the image "
        "quality, optimise the current view or a lens region, calibrate, run the ranking "
        "study, export.  Open the printed address in a browser.  All browser tabs share one "
        "state; run one server per person.",
    )
    p.add_argument(
        "volume",
        nargs="?",
        default="phantom",
        metavar="VOLUME",
        help="'phantom' (default), a file name in --data-dir, or (without --data-dir) a "
        "volume file whose folder becomes the data folder",
    )
    p.add_argument(
        "--orientation", metavar="CODE", help=ORIENTATION_HELP + "; for the volume shown first"
    )
    p.add_argument("--port", type=int, default=8080, help="port to listen on (default 8080)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (127.0.0.1)")
    p.add_argument(
        "--data-dir",
        metavar="DIR",
        help="folder of volumes and spec files, only read (default $DVR_SHARED_DATA or "
        "../shared/data)",
    )
    p.add_argument(
        "--state-dir",
        metavar="DIR",
        help="per-user folder the app writes uploads, saved settings and (by default) "
        "exports into (default: the user state folder, e.g. ~/.local/state/dvr-perception)",
    )
    p.add_argument(
        "--export-dir",
        metavar="DIR",
        help="folder the exports, calibration curves and ranking answers are written to "
        "(default: exports in --state-dir)",
    )
    p.add_argument(
        "--phantom-size",
        type=int,
        default=96,
        metavar="N",
        help="edge length of the built-in phantom (default 96)",
    )
    p.add_argument(
        "--max-upload-mb",
        type=float,
        default=64.0,
        metavar="MB",
        help="largest volume file the upload field accepts, in MB (default 64)",
    )
    p.add_argument(
        "--max-volume-mb",
        type=float,
        default=512.0,
        metavar="MB",
        help="largest voxel data an uploaded volume may hold once decompressed, in MB "
        "(default 512)",
    )
    p.add_argument(
        "--iterations",
        type=int,
        default=10,
        metavar="N",
        help="optimiser iterations per stage (default 10)",
    )
    p.set_defaults(run=run)


def _resolve(args) -> tuple[Path | None, str]:
    data_dir = Path(args.data_dir) if args.data_dir else None
    if data_dir is not None and not data_dir.is_dir():
        raise DVRInputError(f"--data-dir {data_dir}: not a directory")
    volume = args.volume
    if volume == "phantom":
        return data_dir or default_data_dir(), volume
    path = Path(volume)
    if data_dir is None:
        if not path.is_file():
            raise DVRInputError(f"{volume}: no such volume file")
        return path.parent, path.name
    if path.is_file() and (path.is_absolute() or not (data_dir / volume).is_file()):
        # a path to the file (absolute, or from here): it must lie in the data folder
        try:
            return data_dir, path.resolve().relative_to(data_dir.resolve()).as_posix()
        except ValueError:
            raise DVRInputError(
                f"{volume}: not inside --data-dir {data_dir} (the app opens only the files "
                "of its data folder; give the file's name there, or omit --data-dir)"
            ) from None
    if not (data_dir / volume).is_file():
        raise DVRInputError(f"{volume}: no such file in --data-dir {data_dir}")
    return data_dir, volume


def run(args) -> int:
    """Start the server and serve until interrupted."""
    if not 0 <= args.port <= 65535:
        raise DVRInputError(f"--port: expected 0 to 65535, got {args.port}")
    if not 16 <= args.phantom_size <= 512:
        raise DVRInputError(f"--phantom-size: expected 16 to 512, got {args.phantom_size}")
    if not 0 < args.max_upload_mb <= 4096:
        raise DVRInputError(f"--max-upload-mb: expected 0 to 4096, got {args.max_upload_mb}")
    if not 0 < args.max_volume_mb <= 65536:
        raise DVRInputError(f"--max-volume-mb: expected 0 to 65536, got {args.max_volume_mb}")
    if not 1 <= args.iterations <= 200:
        raise DVRInputError(f"--iterations: expected 1 to 200, got {args.iterations}")
    if args.orientation is not None:
        from dvr_perception.volume.orient import parse_orientation

        parse_orientation(args.orientation)  # the other commands' check and error
    data_dir, volume = _resolve(args)
    try:
        from dvr_perception.app import serve
        from dvr_perception.app.core import DVRApp
    except ImportError as exc:
        raise DVRInputError(
            f"the web app needs the 'app' extra: pip install 'dvr-perception[app]' ({exc})"
        ) from None
    log.info("data folder: %s", data_dir)
    app = DVRApp(
        data_dir=data_dir,
        volume=volume,
        orientation=args.orientation,
        export_dir=args.export_dir,
        state_dir=args.state_dir,
        phantom_size=args.phantom_size,
        max_upload_bytes=int(args.max_upload_mb * 1e6),
        max_volume_bytes=int(args.max_volume_mb * 1e6),
        max_iter=args.iterations,
    )
    log.info("writing into: %s", app.session.state_dir)
    serve(app, port=args.port, host=args.host)
    return 0
