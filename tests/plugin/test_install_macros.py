"""``paraview/install_macros.py``: the DVR Perception toolbar lands in ParaView's macro folder.

ParaView 5.11 reads ``$HOME/.config/ParaView/Macros`` at start-up (seen with strace on
Debian's build; Qt's settings folder, so ``$XDG_CONFIG_HOME`` moves it); the GUI test
(``test_view_actions.py``) runs the installed copies as ParaView runs a macro.
"""

from __future__ import annotations

import importlib.util
import json
import runpy
import sys
from pathlib import Path

import pytest

PLUGIN = Path(__file__).resolve().parents[2] / "dvr_perception" / "paraview"
TOOLBAR = ["DVR_Measure_View", "DVR_Optimise_View", "DVR_Refine_Region", "DVR_Undo",
           "DVR_Use_View_Camera"]  # fmt: skip


def _module():
    spec = importlib.util.spec_from_file_location("install_macros", PLUGIN / "install_macros.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_macro_folder_follows_home_and_xdg():
    m = _module()
    assert m.macro_folder({"HOME": "/h"}) == "/h/.config/ParaView/Macros"
    assert m.macro_folder({"HOME": "/h", "XDG_CONFIG_HOME": "/x"}) == "/x/ParaView/Macros"


def test_install_copies_every_macro(tmp_path, capsys):
    m = _module()
    folder = tmp_path / "ParaView" / "Macros"
    assert m.main(["--folder", str(folder)]) == 0
    assert sorted(p.stem for p in folder.iterdir()) == TOOLBAR
    for name in TOOLBAR:
        assert (folder / f"{name}.py").read_bytes() == (
            PLUGIN / "macros" / f"{name}.py"
        ).read_bytes()
    assert "restart ParaView" in capsys.readouterr().out


@pytest.mark.parametrize("name", TOOLBAR)
def test_a_macro_without_the_plugin_says_what_to_load(name, monkeypatch):
    monkeypatch.delitem(sys.modules, "dvr_perception_plugin", raising=False)
    with pytest.raises(RuntimeError, match=r"load dvr_perception_plugin\.py first"):
        runpy.run_path(str(PLUGIN / "macros" / f"{name}.py"), run_name="__main__")


def test_cli_installs_the_macros_and_prints_the_plugin(tmp_path, capsys):
    from dvr_perception.cli import main

    folder = tmp_path / "Macros"
    assert main(["paraview-plugin", "--install-macros", "--macro-folder", str(folder)]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == str(PLUGIN / "dvr_perception_plugin.py")
    assert sorted(p.stem for p in folder.iterdir()) == TOOLBAR
    assert "restart ParaView" in err


def test_install_deps_runs_pip_into_the_pvdeps_folder(tmp_path, monkeypatch, capsys):
    """``--install-deps``: pip --no-deps --target the folder the plugin reads, pinned list."""
    import subprocess

    from dvr_perception import _paraview_compat as compat
    from dvr_perception.cli import main

    deps = tmp_path / "deps"
    monkeypatch.setenv(compat.PVDEPS_ENV, str(deps))
    calls = []

    def fake_pip(cmd, **kwargs):
        calls.append(cmd)
        Path(cmd[cmd.index("--target") + 1]).mkdir()
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(subprocess, "run", fake_pip)
    assert main(["paraview-plugin", "--install-deps", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    (cmd,) = calls
    assert cmd[1:4] == ["-m", "pip", "install"]
    assert {"--no-deps", "--target"} <= set(cmd)
    assert cmd[cmd.index("--target") + 1] == str(deps.resolve())
    assert cmd[cmd.index("-r") + 1] == str(PLUGIN / "pvdeps-requirements.txt")
    assert (got["pvdeps"], got["pvdeps_ready"]) == (str(deps.resolve()), True)


def test_install_deps_reports_a_pip_failure_in_one_line(tmp_path, monkeypatch, capsys):
    import subprocess

    from dvr_perception import _paraview_compat as compat
    from dvr_perception.cli import main

    monkeypatch.setenv(compat.PVDEPS_ENV, str(tmp_path / "deps"))
    monkeypatch.setattr(
        subprocess,
        "run",
        lambda cmd, **k: subprocess.CompletedProcess(cmd, 1, "", "a\nb\nERROR: no such version"),
    )
    assert main(["paraview-plugin", "--install-deps"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--install-deps: pip failed (1): " in err
    assert "ERROR: no such version" in err
