"""Root pytest configuration: applies to the test suite and to the package's doctests."""

from __future__ import annotations

import gc
import sys


def pytest_unconfigure(config):
    """Release pyvista objects while VTK is still alive.

    Tests keep references (e.g. tracebacks of expected errors) until the very end of the
    session; if pyvista's ``__del__`` methods then run during interpreter shutdown, after VTK
    is torn down, they print "Exception ignored" tracebacks.  Closing and collecting here,
    after pytest has dropped its references, avoids that.
    """
    pv = sys.modules.get("pyvista")
    if pv is not None:
        pv.close_all()
    gc.collect()


#: The ParaView plugin's files (``dvr_perception/paraview``) are ParaView scripts: they import
#: ``paraview``, so pytest's doctest collection must not import them in the pip environment.
collect_ignore = ["dvr_perception/paraview"]
