"""Make ``import dvr_perception`` work in ParaView's Python for the plugin and batch scripts.

This folder (``dvr_perception/paraview``) lives inside the package; the package is bound to
``sys.modules`` from its own folder, without putting the folder above it on ``sys.path``: for
an installed wheel that folder is the pip environment's ``site-packages``, whose VTK and numpy
would break pvpython.  Standard library only; the plugin's modules import it first.
"""

import importlib.util
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
PACKAGE = os.path.dirname(HERE)
ROOT = os.path.dirname(PACKAGE)


def bind():
    """Import the ``dvr_perception`` package holding this folder (no-op when imported)."""
    if "dvr_perception" in sys.modules:
        return sys.modules["dvr_perception"]
    spec = importlib.util.spec_from_file_location(
        "dvr_perception",
        os.path.join(PACKAGE, "__init__.py"),
        submodule_search_locations=[PACKAGE],
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["dvr_perception"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules["dvr_perception"]
        raise
    return module
