"""Compatibility shims and ``sys.path`` set-up for running the core inside ParaView's Python.

This is the one place that knows how ParaView's bundled Python differs from the project's pip
environment.  It imports nothing heavy at module import, so the ParaView plugin and
``plugin/pvsite/sitecustomize.py`` can import it before anything else.

Shims (:func:`apply_shims`, idempotent)
    * ``inspect.getargspec``: ParaView 5.11's ``paraview.detail.pythonalgorithm`` (behind
      ``paraview.util.vtkAlgorithm``) imports it, but Python 3.11 removed it.  The alias to
      ``inspect.getfullargspec`` must be in place *before* ParaView loads any Python plugin,
      which is why ``plugin/pvsite/sitecustomize.py`` applies it at interpreter start.
    * ``numpy.in1d``: ParaView 5.11's VTK Python code calls it; numpy >= 2.4 removed it.  It is
      replaced by :func:`numpy.isin` on the flattened input, only when missing.

Paths (:func:`add_paths`)
    The repository root (so ``import dvr_perception`` works) and the pvpython dependency folder
    (``<repo>/.pvdeps`` made by ``make paraview-setup``, or ``$DVR_PERCEPTION_PVDEPS``) are
    put at the front of ``sys.path``, and numba's cache is pointed into that folder, so
    pvpython never shares compiled kernels with the pip environment.  A folder that holds
    ``vtkmodules`` or ``pyvista`` is refused: a second VTK on pvpython's path crashes it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = [
    "PVDEPS_ENV",
    "add_paths",
    "apply_shims",
    "check_pvdeps",
    "pvdeps_dir",
    "repo_root",
    "setup",
]

#: Environment variable that overrides the location of the pvpython dependency folder.
PVDEPS_ENV = "DVR_PERCEPTION_PVDEPS"
#: Packages that must never be on pvpython's path (they bring a second VTK).
_FORBIDDEN = ("vtkmodules", "vtk.py", "pyvista")


def repo_root() -> Path:
    """Return the repository root (the folder holding the ``dvr_perception`` package)."""
    return Path(__file__).resolve().parents[1]


def pvdeps_dir(root: Path | None = None) -> Path:
    """Return the pvpython dependency folder (``$DVR_PERCEPTION_PVDEPS`` or ``<repo>/.pvdeps``).

    Examples
    --------
    >>> pvdeps_dir(Path("/r")).as_posix()  # with DVR_PERCEPTION_PVDEPS unset
    '/r/.pvdeps'
    """
    env = os.environ.get(PVDEPS_ENV, "").strip()
    if env:
        return Path(env).expanduser().resolve()
    return (root or repo_root()) / ".pvdeps"


def check_pvdeps(path: Path) -> str:
    """Return "" if ``path`` may go on pvpython's path, else the reason it may not.

    Examples
    --------
    >>> check_pvdeps(Path("/nonexistent/pvdeps")).startswith("/nonexistent/pvdeps: not found")
    True
    """
    if not path.is_dir():
        return f"{path}: not found (run 'make paraview-setup')"
    bad = [name for name in _FORBIDDEN if (path / name).exists()]
    if bad:
        return (
            f"{path}: holds {', '.join(bad)}; a second VTK crashes pvpython "
            "(install only numpy/scipy/scikit-image/numba there)"
        )
    return ""


def apply_shims() -> None:
    """Patch the Python/numpy differences listed in the module docstring (idempotent)."""
    import inspect

    if not hasattr(inspect, "getargspec"):
        inspect.getargspec = inspect.getfullargspec
    try:
        import numpy
    except ImportError:  # no numpy: nothing to patch (the core will report it)
        return
    if not hasattr(numpy, "in1d") and hasattr(numpy, "isin"):
        setattr(numpy, "in1d", _in1d)  # noqa: B010  (the name is gone from numpy's stubs)


def _in1d(ar1, ar2, assume_unique=False, invert=False, *, kind=None):
    """``numpy.in1d`` as numpy < 2.4 had it: ``isin`` on the flattened first argument.

    Examples
    --------
    >>> _in1d([[1, 2], [3, 4]], [2, 3]).tolist()
    [False, True, True, False]
    """
    import numpy

    return numpy.isin(
        numpy.asarray(ar1).ravel(), ar2, assume_unique=assume_unique, invert=invert, kind=kind
    )


def add_paths(root: Path | None = None) -> list[str]:
    """Put the repository root and the dependency folder first on ``sys.path``.

    Returns the entries added (already present ones are moved to the front).  Raises
    ``RuntimeError`` naming the problem when the dependency folder is unusable.
    """
    root = root or repo_root()
    deps = pvdeps_dir(root)
    why = check_pvdeps(deps)
    if why:
        raise RuntimeError(f"dvr_perception in ParaView: {why}")
    entries = [str(root), str(deps)]
    for entry in reversed(entries):
        while entry in sys.path:
            sys.path.remove(entry)
        sys.path.insert(0, entry)
    return entries


def setup(root: Path | None = None) -> None:
    """:func:`add_paths` then :func:`apply_shims` (what the plugin and batch script call)."""
    add_paths(root)
    apply_shims()
