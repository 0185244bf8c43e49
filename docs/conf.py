"""Sphinx configuration of the dvr_perception manual (``make docs``).

The API reference is generated: :func:`write_api_index` lists the package root's ``__all__``
and every public sub-package and module, and autosummary writes one page per module and
public name from the docstrings (numpydoc).  The tables of measured figures are read from the
JSON files the measuring commands write (``_ext/figures.py``), and the gallery's images are
made by running its scripts (sphinx-gallery).
"""

from __future__ import annotations

import os
import pkgutil
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(DOCS / "_ext"))
os.environ.setdefault("DVR_PERCEPTION_NO_CUDA", "1")  # the gallery runs on the CPU everywhere

import dvr_perception  # noqa: E402

project = "dvr_perception"
author = "the dvr_perception authors"
copyright = "2026, the dvr_perception authors"
release = version = dvr_perception.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
    "figures",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "gallery/*.py", "gallery/README.txt", "examples"]
html_theme = "alabaster"
html_static_path: list[str] = []
html_title = f"dvr_perception {release}"

myst_heading_anchors = 4
myst_enable_extensions = ["colon_fence", "deflist"]
suppress_warnings = ["myst.xref_missing"] if os.environ.get("DVR_DOCS_LAX") else []

autosummary_generate = True
autosummary_ignore_module_all = False  # document what each module's __all__ exports
autosummary_imported_members = False
autodoc_default_options = {"members": True}
autodoc_typehints = "none"  # the numpydoc sections give the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

sphinx_gallery_conf = {
    "examples_dirs": "gallery",
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "image_scrapers": ("matplotlib",),
    "reset_modules": (),
    "abort_on_example_error": True,
    "show_memory": False,
    "plot_gallery": "True",
    "write_computation_times": False,
}

#: Top-level modules and packages left out of the reference: the ParaView scripts (not
#: importable outside ParaView) and the presets' data package.
_NOT_API = {"paraview", "state_files"}


def public_modules() -> list[str]:
    """List the public sub-packages and modules of :mod:`dvr_perception`, sorted."""
    names = [
        f"dvr_perception.{m.name}"
        for m in pkgutil.iter_modules(dvr_perception.__path__)
        if not m.name.startswith("_") and m.name not in _NOT_API
    ]
    return sorted(names)


def root_names() -> list[str]:
    """List the package root's public names by the full names they are documented under.

    The root re-exports them (``dvr_perception.load_volume`` is
    ``dvr_perception.volume.load_volume``); each is documented once, on its sub-package's page,
    and the root's table links there.
    """
    api = dvr_perception._API  # name -> the sub-package that defines it
    names = [f"{api[n]}.{n}" for n in dvr_perception.__all__ if n in api]
    return ["dvr_perception.optimize.optimize", *sorted(names, key=lambda q: q.rsplit(".")[-1])]


def write_api_index() -> None:
    """Write ``api/index.rst``: the root's ``__all__`` and the public modules, recursively."""
    lines = [
        ".. This file is written by docs/conf.py at every build; do not edit it.",
        "",
        "API reference",
        "=============",
        "",
        "Generated from the docstrings. The package root re-exports the main entry points",
        "(``import dvr_perception as dp``); each sub-package's page documents what its",
        "``__all__`` exports, and lists its public modules.",
        "",
        "The package root",
        "----------------",
        "",
        "``dvr_perception.NAME`` for each of these (``dvr_perception.optimize`` is the",
        "optimiser's sub-package and, called, :func:`dvr_perception.optimize.optimize`):",
        "",
        ".. autosummary::",
        "",
        *[f"   ~{n}" for n in root_names()],
        "",
        "Sub-packages and modules",
        "------------------------",
        "",
        ".. autosummary::",
        "   :toctree: generated",
        "   :recursive:",
        "",
        *[f"   {m}" for m in public_modules()],
        "",
    ]
    target = DOCS / "api" / "index.rst"
    target.parent.mkdir(exist_ok=True)
    text = "\n".join(lines)
    if not target.exists() or target.read_text(encoding="utf-8") != text:
        target.write_text(text, encoding="utf-8")


write_api_index()
