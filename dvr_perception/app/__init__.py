"""The trame web app (issue 7): make a volume rendering readable in the browser.

:class:`~dvr_perception.app.core.DVRApp` serves one page with seven screens: choose (or upload)
a volume and edit its structures; read the image-quality numbers, the quality map and each
structure's visible share; optimise opacity (or all stages) for the current view with live
progress, cancel, before/after and a history to undo to any step; draw a lens (rectangle or
circle) and refine only that region with per-structure targets; calibrate the transparency
measure to the viewer; run the paper's ranking task; export.  Start it with
``dvr-perception app`` (:func:`serve`).  Needs the ``app`` extra (trame, trame-vuetify,
trame-vtk, pyvista).  The state is one per server process, shared by all browser tabs.

The server lets in only the holder of a per-run secret, websockets only from its own page, and
bounds every message and upload (:mod:`.security`, :mod:`.uploads`); it reads the data folder
and writes only into a per-user state folder (:mod:`.session`).

This package and :mod:`dvr_perception.plotting` are the only ones importing pyvista/trame;
importing this package does not import trame (the app class is loaded on first use).
"""

from __future__ import annotations

import logging
import os
import signal

__all__ = ["DVRApp", "serve"]


def __getattr__(name):
    if name == "DVRApp":
        from dvr_perception.app.core import DVRApp

        return DVRApp
    raise AttributeError(name)


def __dir__():
    """List the module's names with the lazily imported ``DVRApp`` (for ``dir()``, autodoc)."""
    return sorted({*globals(), *__all__})


def serve(app, *, port: int = 8080, host: str = "127.0.0.1") -> None:
    """Serve ``app`` on ``host:port`` until interrupted (blocking; no browser is opened).

    Prints the address to open, with the app's secret (``...?secret=TOKEN``): the app lets in
    only requests that carry it (see :mod:`dvr_perception.app.security`, installed by
    :class:`~dvr_perception.app.core.DVRApp` when its server binds).  trame would otherwise
    parse ``sys.argv`` for its own options; ``TRAME_ARGS`` is set to nothing so that only
    ``port`` and ``host`` apply, and the idle auto-shutdown is off.
    """
    os.environ["TRAME_ARGS"] = ""
    server = app.server

    def ready(**_):
        _exit_on_sigterm(app)
        shown = "127.0.0.1" if host in ("", "0.0.0.0", "::") else host
        shown = f"[{shown}]" if ":" in shown else shown
        print(
            f"dvr-perception app: open http://{shown}:{server.port}/?secret={app.token}",
            flush=True,
        )

    server.controller.on_server_ready.add(ready)
    server.start(
        port=int(port), host=host, open_browser=False, timeout=0, show_connection_info=False
    )


def _exit_on_sigterm(app) -> None:
    """Make SIGTERM end the server at once, also while the optimiser runs.

    aiohttp's own handler is queued behind the event loop's work, then waits for the open
    connections, and the interpreter then joins the worker threads (an optimisation may run
    for minutes).  Here the handler runs in the main thread at its next Python instruction:
    it cancels the run, logs one line and leaves without joining the worker threads (an
    export being written at that instant may be left incomplete).
    """
    log = logging.getLogger("dvr_perception.app")

    def stop(*_) -> None:
        cancel = getattr(app, "_cancel", None)
        if cancel is not None:
            cancel.set()
        log.info("SIGTERM: server stopped")
        logging.shutdown()
        os._exit(0)

    signal.signal(signal.SIGTERM, stop)
