"""The package's front door: the top-level API, the README's example, ``--version``, extras."""

from __future__ import annotations

import doctest
import re
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

import dvr_perception as dp
from dvr_perception.cli import main

REPO = Path(__file__).resolve().parents[1]


def readme_example() -> str:
    """The python block of the README's "Install and Python API" section."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## Install and Python API\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, blocks
    return blocks[0]


def test_the_readme_example_is_short_and_uses_only_the_root():
    code = [ln for ln in readme_example().splitlines() if ln.startswith(">>> ")]
    assert len(code) <= 10
    assert all("dp._" not in ln and "from dvr_perception." not in ln for ln in code)


@pytest.mark.slow
def test_the_readme_example_runs_as_a_doctest():
    test = doctest.DocTestParser().get_doctest(readme_example(), {}, "README", "README.md", 0)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted >= 7
    assert result.failed == 0


def test_root_names_are_the_subpackages_objects():
    from dvr_perception.measures import MeasureSet, all_measures
    from dvr_perception.optimize import OptimizationResult
    from dvr_perception.optimize import optimize as optimize_function
    from dvr_perception.rays import Camera, analyze
    from dvr_perception.structures import load_spec
    from dvr_perception.volume import load_volume

    assert (dp.load_volume, dp.load_spec, dp.Camera, dp.analyze, dp.all_measures) == (
        load_volume, load_spec, Camera, analyze, all_measures)  # fmt: skip
    assert (dp.MeasureSet, dp.OptimizationResult) == (MeasureSet, OptimizationResult)
    # dp.optimize is the sub-package (as before) and, called, the optimiser
    assert dp.optimize.optimize is optimize_function
    assert callable(dp.optimize)
    for name in dp.__all__:
        assert getattr(dp, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'nonesuch'"):
        dp.nonesuch  # noqa: B018


def test_calling_the_optimize_subpackage_calls_the_function(monkeypatch):
    import dvr_perception.optimize as sub

    seen = []
    monkeypatch.setattr(sub, "optimize", lambda *a, **k: seen.append((a, k)) or "ran")
    assert dp.optimize(1, 2, camera=3) == "ran"
    assert seen == [((1, 2), {"camera": 3})]


def test_importing_the_package_stays_light():
    code = (
        "import sys, dvr_perception as dp; dp.__version__; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & "
        "{'numpy', 'numba', 'vtkmodules', 'scipy', 'matplotlib'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=REPO).stdout  # fmt: skip
    assert out.strip() == "[]"


def test_version_is_one_source(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"dvr-perception {dp.__version__}"
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    assert "version" in pyproject["project"]["dynamic"]
    assert "version" not in pyproject["project"]
    changelog = (REPO / "CHANGELOG.md").read_text(encoding="utf-8")
    releases = re.findall(r"^## \[(\d+\.\d+\.\d+)\]", changelog, flags=re.M)
    assert releases[0] == dp.__version__


def test_extras_say_what_they_are_for():
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    extras = project["optional-dependencies"]

    def names(reqs):
        return {re.split(r"[<>=\[ ;]", r, maxsplit=1)[0].lower() for r in reqs}

    assert "playwright" not in names(extras["app"])  # a test tool, not the app's
    assert "pillow" in names(extras["app"])  # app/export_image.py, app/study.py
    assert "playwright" in names(extras["test"])
    # dev is the other extras by reference, not a copy of their lists
    assert any(r.startswith("dvr-perception[") for r in extras["dev"])
    dev_self = next(r for r in extras["dev"] if r.startswith("dvr-perception["))
    assert {"app", "medical", "test"} <= set(dev_self.split("[")[1].rstrip("]").split(","))
    assert not names(extras["dev"]) & names(extras["app"])
