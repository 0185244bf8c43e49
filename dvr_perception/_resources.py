"""Where the files that ship with the package are: the ParaView plugin, its macros, the presets.

The same paths hold in a source checkout and in an installed wheel:

* ``paraview/`` beside this module holds the ParaView plugin (``dvr_perception_plugin.py``,
  loaded with *Tools > Manage Plugins*), its helper modules, the batch scripts of
  ``dvr-perception pvbatch``, the toolbar macros (``paraview/macros``), the interpreter
  start-up shims (``paraview/pvsite``) and the pins of ParaView's Python dependencies
  (``paraview/pvdeps-requirements.txt``).  They are ParaView scripts, not modules of the
  package: they import ``paraview`` and run only in ParaView's Python.
* The presets (``state_files/*.json``, the structure specs paired with the shared volumes) are
  the repository's top-level ``state_files/`` in a checkout; the wheel carries a copy of the
  ``.json`` files as ``dvr_perception/state_files/`` (``setup.py`` maps the folder in).

Only the standard library is imported, so ParaView's start-up hook can use this module.
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "PACKAGE",
    "checkout_root",
    "macros_dir",
    "paraview_dir",
    "plugin_file",
    "pvdeps_requirements",
    "pvsite_dir",
    "state_files_dir",
]

#: The folder of the ``dvr_perception`` package.
PACKAGE = Path(__file__).resolve().parent


def checkout_root() -> Path | None:
    """Return the source checkout holding the package, or None for an installed package.

    A checkout is recognised by ``pyproject.toml`` and ``state_files/`` beside the package.

    Examples
    --------
    >>> root = checkout_root()
    >>> root is None or (root / "dvr_perception" / "_resources.py").is_file()
    True
    """
    root = PACKAGE.parent
    if (root / "pyproject.toml").is_file() and (root / "state_files").is_dir():
        return root
    return None


def paraview_dir() -> Path:
    """Return the folder of the ParaView plugin and its scripts (``dvr_perception/paraview``).

    Examples
    --------
    >>> (paraview_dir() / "dvr_perception_plugin.py").is_file()
    True
    """
    return PACKAGE / "paraview"


def plugin_file() -> Path:
    """Return the plugin file to load in ParaView (*Tools > Manage Plugins > Load New*).

    Examples
    --------
    >>> plugin_file().name
    'dvr_perception_plugin.py'
    """
    return paraview_dir() / "dvr_perception_plugin.py"


def macros_dir() -> Path:
    """Return the folder of the toolbar macros (copied into ParaView's macro folder).

    Examples
    --------
    >>> sorted(p.name for p in macros_dir().glob("*.py"))[0]
    'DVR_Measure_View.py'
    """
    return paraview_dir() / "macros"


def pvsite_dir() -> Path:
    """Return the folder of ParaView's start-up hook (put first on pvpython's ``PYTHONPATH``).

    Examples
    --------
    >>> (pvsite_dir() / "sitecustomize.py").is_file()
    True
    """
    return paraview_dir() / "pvsite"


def pvdeps_requirements() -> Path:
    """Return the pinned requirements of ParaView's Python (``pip install --target``).

    Examples
    --------
    >>> pvdeps_requirements().is_file()
    True
    """
    return paraview_dir() / "pvdeps-requirements.txt"


def state_files_dir() -> Path:
    """Return the presets folder: the wheel's copy, else the checkout's ``state_files``.

    Examples
    --------
    >>> (state_files_dir() / "cthead.json").is_file()
    True
    """
    packaged = PACKAGE / "state_files"
    if packaged.is_dir():
        return packaged
    return PACKAGE.parent / "state_files"
