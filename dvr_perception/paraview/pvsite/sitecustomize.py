"""Interpreter start-up hook for ParaView's Python (put this folder on PYTHONPATH).

ParaView 5.11 imports ``paraview.detail.pythonalgorithm`` -- which needs
``inspect.getargspec``, gone since Python 3.11 -- *before* it runs a Python plugin file, so
the plugin cannot patch it itself.  Python imports ``sitecustomize`` at start-up, before
ParaView auto-loads plugins from ``PV_PLUGIN_PATH``; this one applies the shims of
``dvr_perception._paraview_compat`` (and makes the package importable when its folder is not
on ``sys.path``) and then runs the system's ``sitecustomize`` (Debian's
apport hook) if there is one further down ``sys.path``.
"""

import os
import sys


def _apply():
    here = os.path.dirname(os.path.abspath(__file__))
    package = os.path.dirname(os.path.dirname(here))  # dvr_perception/paraview/pvsite
    path = os.path.join(package, "_paraview_compat.py")
    import importlib.util

    spec = importlib.util.spec_from_file_location("_dvr_perception_pv_compat_boot", path)
    if spec is None or spec.loader is None:
        return
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.apply_shims()
    # an installed package: its site-packages stays off the path (the pip environment's VTK),
    # so ``import dvr_perception`` is bound to the package holding this folder
    if importlib.util.find_spec("dvr_perception") is None:
        module.bind_package()


def _chain():
    here = os.path.dirname(os.path.abspath(__file__))
    for entry in sys.path:
        if not entry or os.path.abspath(entry) == here:
            continue
        candidate = os.path.join(entry, "sitecustomize.py")
        if os.path.isfile(candidate):
            import runpy

            runpy.run_path(candidate, run_name="sitecustomize")
            return


try:
    _apply()
except Exception as exc:  # never break interpreter start-up
    sys.stderr.write(f"dvr_perception sitecustomize: shims not applied ({exc})\n")
try:
    _chain()
except Exception as exc:
    sys.stderr.write(f"dvr_perception sitecustomize: system sitecustomize failed ({exc})\n")
