"""ParaView compatibility shims, the ParaView environment and ``pvbatch``'s errors (no ParaView).

These run everywhere: they check what the plugin and ``dvr-perception pvbatch`` do *before*
ParaView starts.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path

import numpy as np
import pytest

from dvr_perception import _paraview_compat as compat
from dvr_perception.cli import main
from dvr_perception.cli.pvbatch import _script_args, find_paraview, paraview_env
from dvr_perception.errors import DVRInputError


def test_shims_restore_getargspec_and_in1d(monkeypatch):
    monkeypatch.delattr(inspect, "getargspec", raising=False)
    monkeypatch.delattr(np, "in1d", raising=False)
    compat.apply_shims()
    assert inspect.getargspec is inspect.getfullargspec
    # in1d flattens its first argument (isin keeps the shape)
    in1d = np.in1d  # noqa: NPY201  (the name ParaView 5.11's VTK calls)
    assert in1d(np.array([[1, 5], [3, 7]]), [3, 5]).tolist() == [False, True, True, False]
    assert in1d([1, 2], [2], invert=True).tolist() == [True, False]


def test_shims_keep_an_existing_in1d(monkeypatch):
    def marker(*a, **k):
        return "original"

    monkeypatch.setattr(np, "in1d", marker, raising=False)
    compat.apply_shims()
    assert np.in1d is marker  # noqa: NPY201


def test_pvdeps_folder_with_a_second_vtk_is_refused(tmp_path, monkeypatch):
    deps = tmp_path / "deps"
    (deps / "vtkmodules").mkdir(parents=True)
    monkeypatch.setenv(compat.PVDEPS_ENV, str(deps))
    assert compat.pvdeps_dir() == deps.resolve()
    assert "vtkmodules" in compat.check_pvdeps(deps)
    with pytest.raises(RuntimeError, match="second VTK crashes pvpython"):
        compat.add_paths()
    with pytest.raises(DVRInputError, match="vtkmodules"):
        paraview_env()


def test_add_paths_puts_repo_and_deps_first(tmp_path, monkeypatch):
    deps = tmp_path / "deps"
    deps.mkdir()
    monkeypatch.setenv(compat.PVDEPS_ENV, str(deps))
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")  # recorded, so the test's value is undone
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr("sys.path", ["x", str(deps)])
    added = compat.add_paths(Path("/repo"))
    import sys

    assert sys.path == ["/repo", str(deps.resolve()), "x"]
    assert added == ["/repo", str(deps.resolve())]
    # numba's cache stays where the pip environment keeps it (beside the sources): the same
    # numba version compiles the same machine code, so ParaView reuses it (a separate cache
    # made a fresh machine compile every kernel twice: 100 s a ParaView test)
    assert "NUMBA_CACHE_DIR" not in os.environ


def test_paraview_env_isolates_paraview_from_this_venv(tmp_path, monkeypatch):
    deps = tmp_path / "deps"
    deps.mkdir()
    monkeypatch.setenv(compat.PVDEPS_ENV, str(deps))
    base = {
        "PATH": "/usr/bin",
        "PYTHONPATH": "/venv/site-packages",
        "VIRTUAL_ENV": "/venv",
        "VTK_DEFAULT_OPENGL_WINDOW": "vtkEGLRenderWindow",
    }
    env = paraview_env(display=":7", base=base)
    root = compat.repo_root()
    parts = env["PYTHONPATH"].split(os.pathsep)
    assert parts == [str(root / "dvr_perception" / "paraview" / "pvsite"), str(root),
                     str(deps.resolve())]  # fmt: skip
    assert "VIRTUAL_ENV" not in env
    assert "VTK_DEFAULT_OPENGL_WINDOW" not in env
    assert (env["DISPLAY"], env["PATH"]) == (":7", "/usr/bin")
    assert env[compat.PVDEPS_ENV] == str(deps.resolve())


def test_script_args_forward_the_scene_options():
    from argparse import Namespace

    args = Namespace(
        volume="v.nhdr",
        structures="s.json",
        camera=None,
        size="64x32",
        view="-30,10",
        shade=False,
        sigma=2,
        out="o",
        orientation="LPI",
    )
    assert _script_args(args) == [
        "v.nhdr",
        "--structures",
        "s.json",
        "--size",
        "64x32",
        "--orientation",
        "LPI",
        "--view=-30,10",
        "--no-shade",
        "--sigma",
        "2.0",
        "--out",
        "o",
    ]


def test_pvbatch_without_paraview_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DVR_PERCEPTION_PARAVIEW", str(tmp_path / "no-paraview"))
    with pytest.raises(DVRInputError, match="ParaView is not installed"):
        find_paraview("pvpython")
    assert main(["pvbatch", "phantom", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("dvr-perception: error: ParaView is not installed (pvbatch not")
    assert not (tmp_path / "o").exists()


def test_pvbatch_checks_options_before_starting_paraview(tmp_path, capsys):
    assert main(["pvbatch", "phantom", "--size", "0", "--out", str(tmp_path / "o")]) == 2
    assert "--size" in capsys.readouterr().err
    assert main(["pvbatch", "phantom", "--sigma", "-1", "--out", str(tmp_path / "o")]) == 2
    assert "--sigma: expected a positive number" in capsys.readouterr().err


def _fake_pvbatch(monkeypatch, tmp_path, codes, stderr="( 2.2s) FATL| Signal: SIGABRT"):
    """``dvr-perception pvbatch`` with ParaView replaced: each run exits with the next code."""
    import contextlib
    import json
    import subprocess

    from dvr_perception.cli import pvbatch as mod

    calls = []

    def fake_run(cmd, **_kw):
        code = codes[len(calls)]
        calls.append(cmd)
        out = Path(cmd[cmd.index("--out") + 1])  # the staging folder inside --out
        if code != 0:
            return subprocess.CompletedProcess(cmd, code, "", stderr)
        out.mkdir(exist_ok=True)
        (out / "result.json").write_text(json.dumps({"E_v": 0.1}), encoding="utf-8")
        summary = {"out": str(out), "E_v": 0.1, "E_s": 0.2, "E_t": 0.3}
        return subprocess.CompletedProcess(cmd, 0, json.dumps(summary) + "\n", "")

    monkeypatch.setattr(mod, "find_paraview", lambda name: Path("/fake") / name)
    monkeypatch.setattr(mod, "virtual_display", lambda: contextlib.nullcontext(":99"))
    monkeypatch.setattr(mod, "run_job", lambda cmd, env, timeout, what: fake_run(cmd))
    return calls


def test_pvbatch_retries_when_paraview_dies_of_a_signal(tmp_path, monkeypatch, capsys):
    calls = _fake_pvbatch(monkeypatch, tmp_path, [-6, 0])
    assert main(["pvbatch", "phantom", "--out", str(tmp_path / "o")]) == 0
    assert len(calls) == 2
    out, err = capsys.readouterr()
    assert "E_v = 0.1000" in out
    assert "retrying" in err


def test_pvbatch_reports_a_third_crash(tmp_path, monkeypatch, capsys):
    calls = _fake_pvbatch(monkeypatch, tmp_path, [-6, -6, -6, 0])
    assert main(["pvbatch", "phantom", "--out", str(tmp_path / "o")]) == 1
    assert len(calls) == 3
    assert "pvbatch failed with exit code -6" in capsys.readouterr().err


def test_pvbatch_retries_paraviews_x_abort_under_mpiexec(tmp_path, monkeypatch, capsys):
    """mpiexec reports a rank's abort as 128 + signal; ParaView's X message marks the crash."""
    x_abort = "vtkXOpenGLRenderWindow.:465 ERR| bad X server connection. DISPLAY=:0. Aborting."
    calls = _fake_pvbatch(monkeypatch, tmp_path, [134, 0], stderr=x_abort)
    assert main(["pvbatch", "phantom", "--out", str(tmp_path / "o")]) == 0
    assert len(calls) == 2
    assert "retrying" in capsys.readouterr().err
    # any other failure of the job is reported at once, with ParaView's error line
    calls = _fake_pvbatch(monkeypatch, tmp_path, [1, 0], stderr=f"noise\n{x_abort[:30]} other\n---")
    assert main(["pvbatch", "phantom", "--out", str(tmp_path / "o")]) == 1
    assert len(calls) == 1
    assert "pvbatch failed with exit code 1: vtkXOpenGLRenderWindow" in capsys.readouterr().err


def test_an_installed_packages_site_packages_stays_off_the_path(tmp_path, monkeypatch):
    """The parent of an installed package holds the pip environment's VTK: never on the path."""
    site = tmp_path / "site-packages"
    (site / "vtkmodules").mkdir(parents=True)
    deps = tmp_path / "deps"
    deps.mkdir()
    monkeypatch.setenv(compat.PVDEPS_ENV, str(deps))
    monkeypatch.setattr("sys.path", ["x"])
    assert compat.add_paths(site) == [str(deps.resolve())]
    import sys

    assert sys.path == [str(deps.resolve()), "x"]
    assert not compat.safe_on_path(site)
    assert compat.safe_on_path(tmp_path / "checkout")


def test_default_pvdeps_of_a_checkout_and_of_an_installed_package(tmp_path, monkeypatch):
    monkeypatch.delenv(compat.PVDEPS_ENV, raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    checkout = tmp_path / "checkout"
    (checkout / "dvr_perception").mkdir(parents=True)
    (checkout / "pyproject.toml").write_text("", encoding="utf-8")
    assert compat.pvdeps_dir(checkout) == checkout / ".pvdeps"
    site = tmp_path / "site-packages"
    (site / "dvr_perception").mkdir(parents=True)
    assert compat.pvdeps_dir(site) == tmp_path / "data" / "dvr-perception" / "pvdeps"


def test_the_plugin_binds_the_package_without_its_parent_on_the_path(tmp_path):
    """``dvr_boot.bind`` (plugin, batch scripts) imports the package from its own folder."""
    import subprocess
    import sys

    boot = Path(compat.__file__).resolve().parent / "paraview"
    code = (
        f"import sys; sys.path = [p for p in sys.path if p not in ('', {str(boot.parents[1])!r})]\n"
        f"sys.path.insert(0, {str(boot)!r})\n"
        "import dvr_boot; m = dvr_boot.bind()\n"
        "import dvr_perception._resources as r\n"
        "print(m.__file__); print(r.plugin_file().is_file())"
    )
    env = {"PATH": "/usr/bin:/bin", "PYTHONNOUSERSITE": "1"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.split()
    assert lines == [str(boot.parent / "__init__.py"), "True"]
