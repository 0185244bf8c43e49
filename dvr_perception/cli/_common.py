"""Options and helpers shared by the ``dvr-perception`` sub-commands.

What every command starts from, a volume, its structure spec and a camera, is declared and
loaded by the library's :mod:`dvr_perception.inputs` (shared with the ParaView plugin's batch
scripts); this module adds the command line's glue: the common options, the notes printed after
a command succeeded, JSON output and progress logging.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from dvr_perception._files import json_ready, write_npz
from dvr_perception.inputs import (
    DEFAULT_SIZE,
    ORIENTATION_HELP,
    OptionParser,
    RenderInputs,
    add_input_args,
    check_output_file,
    check_resample,
    make_output_dir,
    parse_factors,
    parse_rect,
    parse_size,
    read_json_file,
)
from dvr_perception.inputs import load_inputs as _load_inputs

__all__ = [
    "DEFAULT_SIZE",
    "ORIENTATION_HELP",
    "PROG",
    "CLIParser",
    "RenderInputs",
    "add_input_args",
    "check_output_file",
    "check_resample",
    "common_parent",
    "emit_json",
    "load_inputs",
    "log_progress",
    "make_output_dir",
    "parse_factors",
    "parse_rect",
    "parse_size",
    "read_json_file",
    "save_buffers",
]

PROG = "dvr-perception"
#: One-line notes for the user (e.g. which spec was chosen and why), printed on stderr by
#: :func:`dvr_perception.cli.main` after the command has succeeded.
NOTES: list[str] = []
log = logging.getLogger("dvr_perception.cli")


def log_progress(what: str):
    """Return a library ``progress`` callback logging ``what: N %`` every quarter (``-v``).

    ``None`` when the log is quiet, so the step skips its reports.
    """
    if not log.isEnabledFor(logging.INFO):
        return None
    last = [0]

    def progress(fraction: float) -> None:
        quarter = int(fraction * 4)
        if quarter > last[0]:
            last[0] = quarter
            log.info("%s: %d %%", what, 25 * quarter)

    return progress


#: The parser of every sub-command: usage errors are one-line DVRInputErrors.
CLIParser = OptionParser


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


def load_inputs(args: argparse.Namespace) -> RenderInputs:
    """:func:`dvr_perception.inputs.load_inputs`, noting the chosen spec for :data:`NOTES`."""
    inputs = _load_inputs(args)
    if inputs.spec_line:  # said once the command has succeeded (an error stays one line)
        NOTES.append(inputs.spec_line)
    return inputs


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
