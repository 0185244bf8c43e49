"""The ``dvr-perception`` command line: ``render``, ``check-renderer``, ``bench``, ``demo``.

Each sub-command lives in its own module with ``add_parser(subparsers, parents)`` and
``run(args) -> int``.  :func:`main` owns the error policy: a
:class:`~dvr_perception.errors.DVRInputError` or an ``OSError`` prints one line
``dvr-perception: error: ...`` and exits 2; anything unexpected prints one line and exits 1
(with a traceback under ``--debug``); a :class:`~dvr_perception.errors.DVRWarning` prints one
line ``dvr-perception: warning: ...``.  Progress goes to stderr (``-v``), results to stdout.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import traceback
import warnings

from dvr_perception._files import Terminated, terminate_as_interrupt
from dvr_perception.cli import (
    app,
    bench,
    check_renderer,
    demo,
    measure,
    optimize,
    pvbatch,
    render,
    report,
)
from dvr_perception.cli._common import PROG, CLIParser, common_parent
from dvr_perception.errors import DVRInputError, DVRWarning
from dvr_perception.structures.spec import printable

__all__ = ["build_parser", "main"]

COMMANDS = (render, check_renderer, bench, demo, measure, optimize, pvbatch, app, report)


def build_parser() -> CLIParser:
    """Build the argument parser with one sub-parser per command."""
    parser = CLIParser(
        prog=PROG,
        description="Perception-based transparency analysis for direct volume rendering.",
    )
    subs = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    parents = [common_parent()]
    for module in COMMANDS:
        module.add_parser(subs, parents)
    return parser


def _one_line(text: str, longest: int = 160) -> str:
    r"""Join ``text`` into one line, escape control characters, cut words over ``longest``.

    Whatever a message quotes (a path, a header value, a name), nothing but printable text
    reaches the terminal: ESC and the other non-printable characters are escaped.

    Examples
    --------
    >>> print(_one_line("bad\nname 'a\x1b[2J'"))
    bad name 'a\x1b[2J'
    """
    words = str(text).split()
    return " ".join(
        printable(w)
        if len(w) <= longest
        else f"{printable(w[: longest - 20], longest - 20)}...({len(w)} characters)"
        for w in words
    )


def _show_warning(message, category, filename, lineno, file=None, line=None):
    text = _one_line(message)
    if not issubclass(category, DVRWarning):
        text = f"{category.__name__}: {text} ({filename}:{lineno})"
    print(f"{PROG}: warning: {text}", file=sys.stderr)


class _PrintableFormatter(logging.Formatter):
    """Log lines with non-printable characters escaped (a logged path cannot drive a terminal)."""

    def format(self, record: logging.LogRecord) -> str:
        return "\n".join(printable(line) for line in super().format(record).splitlines())


@contextlib.contextmanager
def _session(verbose: bool):
    """Route logging to stderr and warnings to one-line messages for one CLI call."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_PrintableFormatter(f"{PROG}: %(message)s"))
    logger = logging.getLogger("dvr_perception")
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO if verbose else logging.WARNING)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", DVRWarning)
            warnings.showwarning = _show_warning
            yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)


def _ignore_sigint() -> None:
    with contextlib.suppress(ValueError):  # not the main thread
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _error(message: str) -> None:
    print(f"{PROG}: error: {_one_line(message)}", file=sys.stderr)


def _os_error_message(exc: OSError) -> str:
    if exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def main(argv=None) -> int:
    """Run the command line; return the exit status (0 ok, 1 unexpected error, 2 bad input).

    Ctrl-C returns 130 and SIGTERM 143 (128 + the signal number, as shells report a process
    the signal ended), after the same clean-up: staged outputs, staging folders and locks are
    removed, so nothing partial is left.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name (default ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status.

    Examples
    --------
    >>> main(["render", "phantom", "--size", "0", "--out", "x.png"])
    2
    """
    argv_given = argv is not None
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    verbose = "-v" in argv or "--verbose" in argv
    with _session(verbose), terminate_as_interrupt():
        from dvr_perception.cli._common import NOTES

        NOTES.clear()
        try:
            args = build_parser().parse_args(argv)
            code = int(args.run(args) or 0)
            for note in NOTES:  # e.g. "structures: preset 'cthead' (data checksum matches)"
                print(note, file=sys.stderr)
            return code
        except SystemExit as exc:  # --help
            return exc.code if isinstance(exc.code, int) else 0
        except DVRInputError as exc:
            _error(str(exc))
            return 2
        except OSError as exc:
            _error(_os_error_message(exc))
            return 2
        except KeyboardInterrupt as exc:
            if not argv_given:  # the process's own entry: a further signal cannot cut the exit
                _ignore_sigint()
            if isinstance(exc, Terminated):  # SIGTERM: cleaned up as for Ctrl-C
                _error("terminated")
                return 128 + signal.SIGTERM
            _error("interrupted")
            return 130
        except Exception as exc:
            if debug:
                traceback.print_exc()
            hint = "" if debug else " (rerun with --debug for a traceback)"
            _error(f"unexpected {type(exc).__name__}: {exc}{hint}")
            return 1
