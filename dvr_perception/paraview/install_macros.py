"""Install the DVR Perception toolbar: copy ``paraview/macros/*.py`` into ParaView's macro folder.

ParaView (5.11) lists every Python file of its user macro folder in the *Macros* menu and on
the *Macro Toolbar* when it starts: ``$XDG_CONFIG_HOME/ParaView/Macros``, by default
``~/.config/ParaView/Macros`` (Qt's settings folder).  Run once, then restart ParaView::

    dvr-perception paraview-plugin --install-macros   # or: make paraview-macros
    dvr-perception paraview-plugin --install-macros --macro-folder DIR

The macros find this folder through the loaded plugin, so the plugin must be loaded (*Tools >
Manage Plugins*, *Auto Load*).  Only the standard library is used: any Python runs it.

**No icons in 5.11.**  ParaView 5.11's macro toolbar shows each macro's name only: its
``pqPythonMacroSupervisor`` has no icon look-up (``iconPathFromFileName``, the ``.svg`` /
``.png`` beside ``NAME.py``, arrived in 5.12), and it lists *every* file of the macro folder
whose name does not start with a dot as a macro, so an icon file copied there would become a
toolbar button that runs the image as Python.  Only the ``.py`` files are copied.
"""

import argparse
import os
import shutil
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE = os.path.join(HERE, "macros")

__all__ = ["install", "macro_folder"]


def macro_folder(environ=None):
    """ParaView's macro folder: ``$XDG_CONFIG_HOME`` (or ``~/.config``)/ParaView/Macros."""
    env = os.environ if environ is None else environ
    base = env.get("XDG_CONFIG_HOME") or os.path.join(
        env.get("HOME") or os.path.expanduser("~"), ".config"
    )
    return os.path.join(base, "ParaView", "Macros")


def install(folder=None):
    """Copy every macro of ``paraview/macros`` into ``folder`` (default :func:`macro_folder`).

    Returns the written paths, sorted.
    """
    folder = folder or macro_folder()
    os.makedirs(folder, exist_ok=True)
    written = []
    for name in sorted(os.listdir(SOURCE)):
        if name.endswith(".py"):
            target = os.path.join(folder, name)
            shutil.copyfile(os.path.join(SOURCE, name), target)
            written.append(target)
    return written


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", help="macro folder (default: ParaView's user macro folder)")
    args = parser.parse_args(argv)
    for path in install(args.folder):
        print(f"installed {path}")
    print("restart ParaView: the macros are on its Macro Toolbar and in the Macros menu")
    return 0


if __name__ == "__main__":
    sys.exit(main())
