"""The wheel is the product: built, installed into a fresh venv outside the repository, used.

The wheel is built from this checkout (``pip wheel --no-deps``) and installed with its
dependencies from the package index into a virtual environment in a temporary folder; every
command then runs there with no ``PYTHONPATH`` and a working directory outside the repository,
so nothing can come from the checkout.  ParaView's ``pvbatch`` loads the plugin from the path
``dvr-perception paraview-plugin`` prints (with the ``.pvdeps`` of ``make paraview-setup``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.plugin.conftest import (  # noqa: F401  (fixtures)
    CROSS_ENV_ABS,
    MARK,
    _private_paraview_settings,
    display,
    paraview,
)

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
SIZE = "32"
#: Variables that would let the checkout or the test's venv leak into the installed package.
_DROP = ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME", "PYTHONSTARTUP")
#: What of the checkout is not source (environments, caches, build output, outputs).
_NOT_SOURCE = (".git", ".venv", ".pvdeps", "build", "dist", "*.egg-info", "__pycache__",
               ".pytest_cache", ".ruff_cache", ".hypothesis", "demo_out", "bench_out")  # fmt: skip


class Installed:
    """The fresh venv with the wheel installed."""

    def __init__(self, root: Path, wheel: Path):
        self.root, self.wheel = root, wheel
        self.bin = root / "venv" / "bin"
        self.work = root / "work"  # the working directory of every command: outside the repo
        self.work.mkdir()
        self.env = {k: v for k, v in os.environ.items() if k not in _DROP}

    def run(self, *args, timeout=900, env=None):
        """Run ``dvr-perception ARGS`` from the venv; return the CompletedProcess."""
        return subprocess.run(
            [str(self.bin / "dvr-perception"), *map(str, args)],
            capture_output=True,
            text=True,
            cwd=self.work,
            env=env or self.env,
            timeout=timeout,
            check=False,
        )

    def json(self, *args, **kwargs) -> dict:
        """Run a command with ``--json``; return its JSON (fails with its output)."""
        proc = self.run(*args, "--json", **kwargs)
        assert proc.returncode == 0, f"{args}: {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        return json.loads(proc.stdout)

    def site_packages(self) -> Path:
        code = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
        out = subprocess.run([str(self.bin / "python"), "-c", code], capture_output=True,
                             text=True, env=self.env, cwd=self.work, check=True).stdout  # fmt: skip
        return Path(out.strip())


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    root = tmp_path_factory.mktemp("wheel")
    assert REPO not in root.parents
    # built from a copy: setuptools' build/ folder in the checkout could hold stale files, and
    # the test writes nothing into the checkout
    source = root / "source"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(*_NOT_SOURCE))
    dist = root / "dist"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    build = subprocess.run([*pip, "wheel", "--no-deps", "-q", "-w", str(dist), str(source)],
                           capture_output=True, text=True, check=False)  # fmt: skip
    assert build.returncode == 0, build.stderr
    (wheel,) = dist.glob("dvr_perception-*.whl")
    subprocess.run([sys.executable, "-m", "venv", str(root / "venv")], check=True)
    out = Installed(root, wheel)
    install = subprocess.run(
        [str(out.bin / "python"), "-m", "pip", "install", "-q", "--disable-pip-version-check",
         str(wheel)],
        capture_output=True, text=True, env=out.env, cwd=out.work, check=False,
    )  # fmt: skip
    assert install.returncode == 0, install.stderr[-3000:]
    return out


def test_the_wheel_holds_the_plugin_macros_presets_and_report(installed):
    names = set(zipfile.ZipFile(installed.wheel).namelist())
    for name in (
        "dvr_perception/paraview/dvr_perception_plugin.py",
        "dvr_perception/paraview/dvr_boot.py",
        "dvr_perception/paraview/batch_measure.py",
        "dvr_perception/paraview/pvsite/sitecustomize.py",
        "dvr_perception/paraview/pvdeps-requirements.txt",
        "dvr_perception/paraview/macros/DVR_Undo.py",
        "dvr_perception/benchmarks/report.py",
        "dvr_perception/benchmarks/observations.md",
        "dvr_perception/state_files/cthead.json",
    ):
        assert name in names, name
    presets = {p.name for p in (REPO / "state_files").glob("*.json")}
    assert {n.rsplit("/", 1)[1] for n in names if n.startswith("dvr_perception/state_files/")
            and n.endswith(".json")} == presets  # fmt: skip
    assert not any(n.startswith(("tests/", "plugin/", "benchmarks/")) for n in names)
    # the ParaView state scripts of state_files/ load a checkout's plugin: not in the wheel
    assert not [n for n in names if n.startswith("dvr_perception/state_files/")
                and not n.endswith(".json")]  # fmt: skip


@pytest.fixture(scope="module")
def measured(installed, shared_data) -> dict:
    """The installed ``dvr-perception measure`` of neghip (its preset paired), ``--json``."""
    return installed.json("measure", shared_data / "neghip.nhdr", "--size", SIZE)


def test_the_installed_package_runs_outside_the_repository(installed, shared_data, measured):
    site = installed.site_packages()
    assert REPO not in site.parents
    version = installed.run("--version")
    assert version.returncode == 0, version.stderr
    import dvr_perception

    assert version.stdout.strip() == f"dvr-perception {dvr_perception.__version__}"

    plugin = installed.run("paraview-plugin")
    assert plugin.returncode == 0, plugin.stderr
    path = Path(plugin.stdout.strip())
    assert path == site / "dvr_perception" / "paraview" / "dvr_perception_plugin.py"
    assert path.is_file()

    demo = installed.json("demo", "--out", "demo", "--size", SIZE)
    assert (installed.work / "demo" / "phantom.png").is_file()
    assert demo["optimize"]["final"]["E"] < demo["optimize"]["initial"]["E"]

    volume = shared_data / "neghip.nhdr"
    got = measured
    # the preset paired with the volume comes from the wheel's copy of state_files/
    assert got["spec"] == str(site / "dvr_perception" / "state_files" / "neghip.json")
    assert 0 < got["E_v"] <= 2
    assert 0 <= got["E_s"] <= 1

    from dvr_perception.cli import main

    here = installed.root / "here.json"
    with open(here, "w", encoding="utf-8") as fh, _stdout(fh):
        assert main(["measure", str(volume), "--size", SIZE, "--json"]) == 0
    ours = json.loads(here.read_text(encoding="utf-8"))
    for term in ("E_v", "E_s", "E_t"):  # same code, same numbers, installed or not
        assert got[term] == pytest.approx(ours[term], abs=1e-9), term

    opt = installed.json("optimize", volume, "--size", SIZE, "--stages", "opacity",
                         "--out", "opt")  # fmt: skip
    assert (installed.work / "opt" / "result.json").is_file()
    assert opt["final"]["E"] <= opt["initial"]["E"]
    assert opt["spec"] == got["spec"]

    # the report code and its hand-written observations come with the wheel
    report = installed.work / "report"
    report.mkdir()
    shutil.copy(REPO / "benchmarks" / "summary.json", report / "summary.json")
    proc = installed.run("report", "--markdown-only", "--out", report)
    assert proc.returncode == 0, proc.stderr
    observations = (REPO / "dvr_perception" / "benchmarks" / "observations.md").read_text(
        encoding="utf-8"
    )
    line = next(ln for ln in observations.split("\n### ", 1)[1].splitlines()[1:] if ln.strip())
    assert line in (report / "REPORT.md").read_text(encoding="utf-8")


class _stdout:
    """Send ``sys.stdout`` to ``fh`` for a block."""

    def __init__(self, fh):
        self.fh = fh

    def __enter__(self):
        self.old, sys.stdout = sys.stdout, self.fh

    def __exit__(self, *exc):
        sys.stdout = self.old


def test_pvbatch_loads_the_plugin_from_the_printed_path(
    installed,
    measured,
    shared_data,
    paraview,  # noqa: F811
    display,  # noqa: F811
):
    plugin = Path(installed.run("paraview-plugin").stdout.strip())
    site = installed.site_packages()
    pvsite = installed.run("paraview-plugin", "--json")
    info = json.loads(pvsite.stdout)
    deps = paraview.env["DVR_PERCEPTION_PVDEPS"]
    env = {k: v for k, v in paraview.env.items() if k not in _DROP}
    env.update(PYTHONPATH=os.pathsep.join([info["pvsite"], deps]), DISPLAY=display)
    script = installed.work / "load_plugin.py"
    script.write_text(
        f"""
import json, sys
from paraview.simple import *
LoadPlugin({str(plugin)!r}, ns=globals())
import dvr_perception, numpy
from dvr_perception.structures import make_phantom
vol, spec = make_phantom()
files = {{name: getattr(m, "__file__", None) or "" for name, m in list(sys.modules.items())}}
leaked = sorted(name for name, f in files.items() if f.startswith({str(site)!r})
                and not f.startswith({str(site / "dvr_perception")!r}))
print({MARK!r} + json.dumps({{
    "package": dvr_perception.__file__,
    "filters": [n for n in ("PerceptionMeasures", "OptimizeTransferFunction") if n in globals()],
    "leaked": leaked, "numpy": numpy.__file__, "shape": list(vol.data.shape),
}}), flush=True)
""",
        encoding="utf-8",
    )
    proc = paraview.call([str(paraview.pvbatch), str(script)], env=env, cwd=installed.work,
                         capture_output=True, text=True, timeout=600, check=False)  # fmt: skip
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(MARK)]
    assert proc.returncode == 0, f"{proc.stdout}\n{proc.stderr}"
    assert lines, f"{proc.stdout}\n{proc.stderr}"
    got = json.loads(lines[-1][len(MARK) :])
    assert got["package"] == str(site / "dvr_perception" / "__init__.py")
    assert got["filters"] == ["PerceptionMeasures", "OptimizeTransferFunction"]
    assert got["leaked"] == []  # nothing of the pip environment's site-packages (VTK, numpy)
    assert not got["numpy"].startswith(str(site))
    assert all(n > 0 for n in got["shape"])

    # the wheel's own batch script, through its CLI: the plugin's filter measures the volume
    env_cli = dict(installed.env, DVR_PERCEPTION_PVDEPS=deps)
    env_cli.pop("VTK_DEFAULT_OPENGL_WINDOW", None)
    out = installed.json("pvbatch", shared_data / "neghip.nhdr", "--size", SIZE, "--out", "pv",
                         "--no-screenshot", env=env_cli)  # fmt: skip
    assert out["spec"] == measured["spec"]  # the wheel's preset, in ParaView too
    for term in ("E_v", "E_s", "E_t"):
        assert out[term] == pytest.approx(measured[term], abs=CROSS_ENV_ABS), term
