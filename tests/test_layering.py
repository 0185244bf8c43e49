"""No package of dvr_perception imports a package above it, and nothing outside cli/ imports cli.

The layers, from the bottom (a package may import the packages of its own and of lower
layers, never of a higher one):

0. the ground floor: the top-level modules ``dvr_perception/_*.py`` (files, memory limit,
   VTK and numba loading, figures, timing, resources), ``errors`` and ``parallel``;
1. ``volume``; 2. ``structures`` (with the built-in phantom and presets); 3. ``export`` (the
   spec as VTK transfer functions and other tools' files: needs only structures); 4. ``rays``;
   5. ``measures``; 6. ``optimize``;
7. above the optimiser, below the front ends: ``distributed`` (the MPI driver),
   ``calibration`` (the psychophysics study's stimuli and curve) and ``inputs`` (the loader of a
   volume, spec and camera every front end starts from); none imports another;
8. the front ends: ``filters``, ``plotting``, ``benchmarks``, ``app``, ``paraview``, ``cli``.
   Among them only the edges of :data:`FRONT_END_EDGES` are allowed: the command line starts
   the others (the app, the report, the plugin's paths), the app draws with ``plotting`` and
   the ParaView plugin wraps ``filters``.

Every ``import`` / ``from ... import`` is read with :mod:`ast`, those inside functions (lazy
imports) included, and so is ``importlib.import_module("dvr_perception....")`` with a constant
name.  Deprecated aliases, which import their new home lazily for one release, are the only
exceptions (:data:`DEPRECATED_ALIASES`).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dvr_perception"

GROUND = 0
LAYERS = {
    "errors": GROUND,
    "parallel": GROUND,
    "volume": 1,
    "structures": 2,
    "export": 3,
    "rays": 4,
    "measures": 5,
    "optimize": 6,
    "distributed": 7,
    "calibration": 7,
    "inputs": 7,
    "filters": 8,
    "plotting": 8,
    "benchmarks": 8,
    "app": 8,
    "paraview": 8,
    "cli": 8,
}
#: Imports allowed between two units of the same layer (importer -> imported).
FRONT_END_EDGES = {
    "cli": {"app", "benchmarks", "filters", "paraview", "plotting"},
    "app": {"plotting"},
    "paraview": {"filters"},
}
#: (file relative to the package, imported module): deprecated aliases that import their new
#: home lazily; remove each with its alias (one release after 0.1).
DEPRECATED_ALIASES = {
    ("volume/__init__.py", "dvr_perception.structures.phantom"),
    ("volume/phantom.py", "dvr_perception.structures.phantom"),
    ("structures/transfer.py", "dvr_perception.export"),
    ("rays/ranks.py", "dvr_perception.distributed"),
}


def unit_of(rel: Path) -> str | None:
    """The layering unit of a file (``rel`` relative to the package); None: the root module."""
    parts = rel.parts
    if len(parts) == 1:
        name = parts[0].removesuffix(".py")
        return None if name == "__init__" else name
    return parts[0]


def layer_of(unit: str, layers=LAYERS) -> int:
    """The layer of a unit: a top-level ``_*.py`` module is on the ground floor."""
    if unit.startswith("_"):
        return GROUND
    if unit not in layers:
        raise KeyError(f"{unit}: not placed in a layer (add it to LAYERS in {__file__})")
    return layers[unit]


def _imported(tree: ast.AST, module: str, package: str):
    """``(line, imported module)`` of every import in ``tree``, lazy ones included."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing module's package
                base = module.split(".")[: -node.level]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            yield node.lineno, name
            for alias in node.names:  # ``from dvr_perception import cli``
                if name == package:
                    yield node.lineno, f"{package}.{alias.name}"
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            yield node.lineno, node.args[0].value


def violations(
    root: Path,
    package: str = "dvr_perception",
    *,
    layers=LAYERS,
    edges=FRONT_END_EDGES,
    allowed=frozenset(),
) -> list[str]:
    """Every import under ``root`` (the package folder) that reaches a layer above its own."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        unit = unit_of(rel)
        if unit is None:
            continue
        here = layer_of(unit, layers)
        module = ".".join([package, *rel.with_suffix("").parts])  # pkg.sub.__init__ too
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for line, name in _imported(tree, module, package):
            parts = name.split(".")
            if parts[0] != package or len(parts) < 2:
                continue
            target = parts[1]
            if target == unit or (rel.as_posix(), name) in allowed:
                continue
            there = layer_of(target, layers)
            if target == "cli" and unit != "cli":
                out.append(f"{rel}:{line}: imports {name} (only cli/ may import the CLI)")
            elif there > here or (
                there == here and here != GROUND and target not in edges.get(unit, ())
            ):
                out.append(f"{rel}:{line}: {unit} (layer {here}) imports {name} (layer {there})")
    return out


def test_no_package_imports_a_package_above_it():
    assert violations(PACKAGE, allowed=DEPRECATED_ALIASES) == []


def test_every_unit_has_a_layer():
    units = {unit_of(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py")} - {None}
    unplaced = sorted(u for u in units if not u.startswith("_") and u not in LAYERS)
    assert unplaced == []


def test_nothing_outside_cli_imports_the_cli():
    found = [v for v in violations(PACKAGE, allowed=DEPRECATED_ALIASES) if "cli" in v]
    assert found == []
    users = []
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] == "cli":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        users += [f"{rel}:{ln}" for ln, name in _imported(tree, "x", "dvr_perception")
                  if name.startswith("dvr_perception.cli")]  # fmt: skip
    assert users == []


def test_the_deprecated_aliases_still_exist():
    # an alias removed from the code must leave the exception list too
    for rel, name in DEPRECATED_ALIASES:
        text = (PACKAGE / rel).read_text(encoding="utf-8")
        package, _, module = name.rpartition(".")
        assert f"from {name} import" in text or f"from {package} import {module}" in text, (
            rel,
            name,
        )


# -- the checker itself, on a tiny fake package --------------------------------------------------
def _tree(tmp_path: Path, files: dict) -> Path:
    root = tmp_path / "pkg"
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text, encoding="utf-8")
    return root


FAKE_LAYERS = {"errors": 0, "low": 1, "high": 2, "cli": 3, "app": 3}


def test_the_checker_accepts_downward_imports(tmp_path):
    root = _tree(
        tmp_path,
        {
            "__init__.py": "",
            "_files.py": "from pkg.errors import E\n",
            "errors.py": "",
            "low/__init__.py": "from pkg import errors\nfrom pkg._files import f\n",
            "high/core.py": "from pkg.low import x\nfrom . import other\n",
            "cli/__init__.py": "from pkg.app import run\nfrom pkg.high.core import y\n",
            "app/__init__.py": "",
        },
    )
    assert violations(root, "pkg", layers=FAKE_LAYERS, edges={"cli": {"app"}}) == []


@pytest.mark.parametrize(
    ("rel", "text", "expected"),
    [
        ("low/a.py", "from pkg.high import core\n", "low (layer 1) imports pkg.high"),
        ("low/a.py", "def f():\n    import pkg.high.core\n", "low/a.py:2: low (layer 1)"),
        ("low/a.py", "import importlib\nimportlib.import_module('pkg.high')\n", "pkg.high"),
        ("low/a.py", "from pkg import high\n", "imports pkg.high (layer 2)"),
        ("low/sub/a.py", "from ...high import core\n", "imports pkg.high"),
        ("errors.py", "from pkg.low import x\n", "errors (layer 0) imports pkg.low"),
        ("_files.py", "def f():\n    from pkg.low import x\n", "_files (layer 0)"),
        ("high/b.py", "from pkg.cli import main\n", "only cli/ may import the CLI"),
        ("app/b.py", "from pkg.cli import main\n", "only cli/ may import the CLI"),
        ("app/c.py", "from pkg.high import core\nfrom pkg.cli._x import y\n", "app/c.py:2"),
    ],
)
def test_the_checker_finds_a_planted_violation(tmp_path, rel, text, expected):
    files = {"__init__.py": "", "errors.py": "", "low/__init__.py": "", "high/core.py": ""}
    files.update({"cli/__init__.py": "", "app/__init__.py": "", rel: text})
    root = _tree(tmp_path, files)
    found = violations(root, "pkg", layers=FAKE_LAYERS, edges={"cli": {"app"}})
    assert len(found) == 1, found
    assert expected in found[0]


def test_the_checker_refuses_a_same_layer_import_without_an_edge(tmp_path):
    root = _tree(tmp_path, {"cli/a.py": "", "app/a.py": "from pkg.cli import a\n"})
    assert violations(root, "pkg", layers=FAKE_LAYERS, edges={"cli": {"app"}}) != []
    root = _tree(tmp_path, {"cli/a.py": "from pkg.app import a\n", "app/a.py": ""})
    assert violations(root, "pkg", layers=FAKE_LAYERS, edges={}) == [
        "cli/a.py:1: cli (layer 3) imports pkg.app (layer 3)"
    ]


def test_the_checker_needs_every_unit_placed(tmp_path):
    root = _tree(tmp_path, {"stray/a.py": "import os\n"})
    with pytest.raises(KeyError, match="stray: not placed"):
        violations(root, "pkg", layers=FAKE_LAYERS)


def test_the_real_package_with_a_planted_violation_fails(tmp_path):
    import shutil

    copy = tmp_path / "dvr_perception"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "*.json"))
    assert violations(copy, allowed=DEPRECATED_ALIASES) == []
    target = copy / "volume" / "volume.py"
    planted = "\n\ndef _f():\n    from dvr_perception.rays import memory\n"
    target.write_text(target.read_text(encoding="utf-8") + planted, encoding="utf-8")
    found = violations(copy, allowed=DEPRECATED_ALIASES)
    assert len(found) == 1
    assert found[0].startswith("volume/volume.py:")
    assert "volume (layer 1) imports dvr_perception.rays (layer 4)" in found[0]
