"""Compatibility shims and ``sys.path`` set-up for running the core inside ParaView's Python.

This is the one place that knows how ParaView's bundled Python differs from the project's pip
environment.  It imports nothing heavy at module import, so the ParaView plugin and
``paraview/pvsite/sitecustomize.py`` (in this package) can import it before anything else.

Shims (:func:`apply_shims`, idempotent)
    * ``inspect.getargspec``: ParaView 5.11's ``paraview.detail.pythonalgorithm`` (behind
      ``paraview.util.vtkAlgorithm``) imports it, but Python 3.11 removed it.  The alias to
      ``inspect.getfullargspec`` must be in place *before* ParaView loads any Python plugin,
      which is why ``paraview/pvsite/sitecustomize.py`` applies it at interpreter start.
    * ``numpy.in1d``: ParaView 5.11's VTK Python code calls it; numpy >= 2.4 removed it.  It is
      replaced by :func:`numpy.isin` on the flattened input, only when missing.

Paths (:func:`add_paths`)
    The pvpython dependency folder (``$DVR_PERCEPTION_PVDEPS``; by default ``<repo>/.pvdeps``
    made by ``make paraview-setup`` in a checkout, ``~/.local/share/dvr-perception/pvdeps``
    made by ``dvr-perception paraview-plugin --install-deps`` for an installed wheel) is put at
    the front of ``sys.path``, and numba's cache is pointed into that folder, so pvpython never
    shares compiled kernels with the pip environment.  A folder that holds ``vtkmodules`` or
    ``pyvista`` is refused: a second VTK on pvpython's path crashes it.  The folder holding the
    package goes on ``sys.path`` too when it is a checkout; an installed package's
    ``site-packages`` (the pip environment's VTK and numpy) never does: :func:`bind_package`
    imports the package from its own folder instead.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = [
    "PVDEPS_ENV",
    "add_paths",
    "apply_shims",
    "bind_package",
    "check_pvdeps",
    "is_checkout",
    "pvdeps_dir",
    "repo_root",
    "safe_on_path",
    "setup",
]

#: Environment variable that overrides the location of the pvpython dependency folder.
PVDEPS_ENV = "DVR_PERCEPTION_PVDEPS"
#: Packages that must never be on pvpython's path (they bring a second VTK).
_FORBIDDEN = ("vtkmodules", "vtk.py", "pyvista")


def repo_root() -> Path:
    """Return the folder holding the ``dvr_perception`` package (a checkout or site-packages)."""
    return Path(__file__).resolve().parents[1]


def is_checkout(root: Path) -> bool:
    """Return True if ``root`` is a source checkout (``pyproject.toml`` beside the package).

    Examples
    --------
    >>> is_checkout(Path("/nonexistent"))
    False
    """
    return (root / "pyproject.toml").is_file() and (root / "dvr_perception").is_dir()


def pvdeps_dir(root: Path | None = None) -> Path:
    """Return the pvpython dependency folder (see the module docstring for the default).

    Examples
    --------
    >>> pvdeps_dir(Path("/r")).name  # with DVR_PERCEPTION_PVDEPS unset, not a checkout
    'pvdeps'
    """
    env = os.environ.get(PVDEPS_ENV, "").strip()
    if env:
        return Path(env).expanduser().resolve()
    root = root or repo_root()
    if is_checkout(root):
        return root / ".pvdeps"
    data = os.environ.get("XDG_DATA_HOME", "").strip() or os.path.join(
        os.path.expanduser("~"), ".local", "share"
    )
    return Path(data) / "dvr-perception" / "pvdeps"


def safe_on_path(root: Path) -> bool:
    """Return True if ``root`` holds nothing that must stay off pvpython's path.

    Examples
    --------
    >>> safe_on_path(Path("/nonexistent"))
    True
    """
    return not any((root / name).exists() for name in _FORBIDDEN)


def bind_package() -> None:
    """Make ``import dvr_perception`` import the package that holds this module.

    Without putting its parent folder on ``sys.path``: the parent of an installed package is
    the pip environment's ``site-packages``, whose VTK and numpy would break pvpython.  A
    no-op when ``dvr_perception`` is already imported.
    """
    if "dvr_perception" in sys.modules:
        return
    import importlib.util

    package = Path(__file__).resolve().parent
    spec = importlib.util.spec_from_file_location(
        "dvr_perception", package / "__init__.py", submodule_search_locations=[str(package)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["dvr_perception"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules["dvr_perception"]
        raise


def check_pvdeps(path: Path) -> str:
    """Return "" if ``path`` may go on pvpython's path, else the reason it may not.

    Examples
    --------
    >>> check_pvdeps(Path("/nonexistent/pvdeps")).startswith("/nonexistent/pvdeps: not found")
    True
    """
    if not path.is_dir():
        return (
            f"{path}: not found (run 'make paraview-setup' in a checkout, or "
            "'dvr-perception paraview-plugin --install-deps')"
        )
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
    """Put the package's folder (when safe) and the dependency folder first on ``sys.path``.

    Returns the entries added (already present ones are moved to the front).  Raises
    ``RuntimeError`` naming the problem when the dependency folder is unusable.
    """
    root = root or repo_root()
    deps = pvdeps_dir(root)
    why = check_pvdeps(deps)
    if why:
        raise RuntimeError(f"dvr_perception in ParaView: {why}")
    entries = [str(root), str(deps)] if safe_on_path(root) else [str(deps)]
    for entry in reversed(entries):
        while entry in sys.path:
            sys.path.remove(entry)
        sys.path.insert(0, entry)
    return entries


def setup(root: Path | None = None) -> None:
    """:func:`add_paths`, :func:`apply_shims`, :func:`bind_package` (the plugin's set-up)."""
    add_paths(root)
    apply_shims()
    bind_package()
