"""``dvr-perception paraview-plugin``: where the ParaView plugin is, and its set-up.

The plugin ships inside the package (``dvr_perception/paraview``), so a ``pip install``
brings it; this command prints the file to load in ParaView's *Tools > Manage Plugins > Load
New* (tick *Auto Load*).  ``--install-macros`` copies the DVR Perception toolbar's macros
into ParaView's user macro folder; ``--install-deps`` installs the core's dependencies for
ParaView's own Python (``pip install --no-deps --target``, the pins of
``paraview/pvdeps-requirements.txt``) into the folder the plugin reads them from.
``make paraview-setup`` and ``make paraview-macros`` run this command.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
from pathlib import Path

from dvr_perception import _paraview_compat, _resources
from dvr_perception.cli._common import emit_json
from dvr_perception.errors import DVRInputError

__all__ = ["add_parser", "install_deps", "install_macros", "run"]

EXAMPLE = """examples:
  dvr-perception paraview-plugin                   # the file for Tools > Manage Plugins
  dvr-perception paraview-plugin --install-macros  # the toolbar; restart ParaView
  dvr-perception paraview-plugin --install-deps    # scipy, numba, ... for ParaView's Python
"""


def add_parser(subparsers, parents) -> None:
    """Register the ``paraview-plugin`` sub-command."""
    p = subparsers.add_parser(
        "paraview-plugin",
        parents=parents,
        help="print the ParaView plugin file to load (Tools > Manage Plugins); install macros",
        description="Print the path of the ParaView plugin shipped in this package, the file "
        "to load with Tools > Manage Plugins > Load New (tick Auto Load).",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--install-macros",
        action="store_true",
        help="copy the DVR Perception toolbar macros into ParaView's macro folder",
    )
    p.add_argument(
        "--macro-folder",
        metavar="DIR",
        default=None,
        help="macro folder for --install-macros (default: $XDG_CONFIG_HOME/ParaView/Macros)",
    )
    p.add_argument(
        "--install-deps",
        action="store_true",
        help="pip-install the core's dependencies for ParaView's Python into the folder the "
        "plugin reads ($DVR_PERCEPTION_PVDEPS, else .pvdeps in a checkout, else "
        "~/.local/share/dvr-perception/pvdeps)",
    )
    p.set_defaults(run=run)


def _macro_module():
    """Load ``paraview/install_macros.py`` (a standalone script of the plugin folder)."""
    path = _resources.paraview_dir() / "install_macros.py"
    spec = importlib.util.spec_from_file_location("_dvr_install_macros", path)
    if spec is None or spec.loader is None:
        raise DVRInputError(f"{path}: not found; the package is incomplete (reinstall it)")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def install_macros(folder: str | None = None) -> list[str]:
    """Copy the toolbar macros into ``folder`` (default ParaView's); return the written paths."""
    return _macro_module().install(folder)


def install_deps(target: Path) -> list[str]:
    """Install ParaView's Python dependencies into ``target``; return the pip command.

    Raises :class:`~dvr_perception.errors.DVRInputError` when pip fails (its last lines).
    """
    cmd = [
        sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
        "--no-deps", "--upgrade", "--target", str(target),
        "-r", str(_resources.pvdeps_requirements()),
    ]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        tail = " | ".join((proc.stderr or proc.stdout).strip().splitlines()[-3:])
        raise DVRInputError(f"--install-deps: pip failed ({proc.returncode}): {tail}")
    why = _paraview_compat.check_pvdeps(target)
    if why:
        raise DVRInputError(f"--install-deps: {why}")
    return cmd


def run(args: argparse.Namespace) -> int:
    """Execute ``paraview-plugin``."""
    plugin = _resources.plugin_file()
    if not plugin.is_file():
        raise DVRInputError(f"{plugin}: not found; the package is incomplete (reinstall it)")
    deps = _paraview_compat.pvdeps_dir()
    result = {"plugin": str(plugin), "pvsite": str(_resources.pvsite_dir()), "pvdeps": str(deps)}
    if args.install_deps:
        install_deps(deps)
        result["installed_deps"] = True
    if args.install_macros:
        result["macros"] = install_macros(args.macro_folder)
    result["pvdeps_ready"] = not _paraview_compat.check_pvdeps(deps)
    if args.json:
        emit_json(result)
        return 0
    for path in result.get("macros", []):
        print(f"installed macro {path}", file=sys.stderr)
    if result.get("macros"):
        print("restart ParaView: the macros are on its Macro Toolbar", file=sys.stderr)
    if not result["pvdeps_ready"]:
        print(
            f"note: ParaView's Python needs the core's dependencies in {deps}: run "
            "'dvr-perception paraview-plugin --install-deps' (or set DVR_PERCEPTION_PVDEPS)",
            file=sys.stderr,
        )
    print(
        f"load it in ParaView (Tools > Manage Plugins > Load New) started with "
        f"PYTHONPATH={result['pvsite']}",
        file=sys.stderr,
    )
    print(plugin)
    return 0
