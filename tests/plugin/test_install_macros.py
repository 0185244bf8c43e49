"""``paraview/install_macros.py``: the DVR Perception toolbar lands in ParaView's macro folder.

ParaView 5.11 reads ``$HOME/.config/ParaView/Macros`` at start-up (seen with strace on
Debian's build; Qt's settings folder, so ``$XDG_CONFIG_HOME`` moves it); the GUI test
(``test_view_actions.py``) runs the installed copies as ParaView runs a macro.
"""

from __future__ import annotations

import importlib.util
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
