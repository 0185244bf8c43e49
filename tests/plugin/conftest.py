"""Fixtures for the ParaView plugin tests.

``paraview`` finds the installed ParaView (``pvpython``, ``pvbatch``) and the environment its
Python needs (:func:`dvr_perception.cli.pvbatch.paraview_env`).  Like ``shared_data`` and
``vtk_can_render`` in ``tests/conftest.py`` it skips on a developer machine without ParaView
(or without ``make paraview-setup``'s ``.pvdeps``) but FAILS under ``CI=true``, where
``make test`` installs both.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
MARK = "@@RESULT@@ "  # must match test_paraview.MARK
#: Tolerance of pvpython's E terms against the library's in the pip environment (issue 18.5).
#: ParaView 5.11 brings numpy 1.24, the venv numpy 2.x.  Seen 2026-12-01: E_s 1.1e-6 to 1.8e-6
#: apart (tooth), 1.3e-4 on fuel (numpy's SIMD arctan2/arcsin in the normal encoder); since the
#: encoder's angles on rounding boundaries come from the C library, 2e-16 at most on the 16
#: shared volumes at two views (256²; ``test_xenv.py``).
CROSS_ENV_ABS = 1e-5


#: What marks a VTK/ParaView warning or error in a run's output: the text vtkOutputWindow
#: prints ("Warning: In file, line" / "ERROR: In ...", "Generic Warning"), and the log lines of
#: ParaView's logger ("(  1.234s) [paraview  ]  file.cxx:85  WARN| ...", "ERR|").
VTK_MESSAGE_MARKERS = ("Warning: In", "ERROR: In", "vtkOutputWindow", "Generic Warning",
                       "WARN|", "ERR|")  # fmt: skip
#: Message lines that come from ParaView itself, not from the project's code, and are allowed.
#: Each entry is a substring of the line and the reason it is ParaView's own.  Empty: no run
#: of the plugin tests prints any VTK warning since the lookup-table and premultiplied-check
#: fixes (the colour nodes kept one GPU table entry apart, the engine's image not checked as
#: if it were of unknown origin).
ALLOWED_VTK_MESSAGES: dict[str, str] = {}


def vtk_messages(text: str, allow: dict | None = None) -> list[str]:
    """Return the lines of ``text`` that are VTK/ParaView warnings or errors, bar allowed ones."""
    allowed = ALLOWED_VTK_MESSAGES if allow is None else {**ALLOWED_VTK_MESSAGES, **allow}
    lines = [ln for ln in (text or "").splitlines() if any(m in ln for m in VTK_MESSAGE_MARKERS)]
    return [ln for ln in lines if not any(a in ln for a in allowed)]


def assert_no_vtk_messages(text: str, allow: dict | None = None) -> None:
    """Fail with the offending lines if a ParaView run printed a VTK warning or error."""
    bad = vtk_messages(text, allow)
    assert not bad, "ParaView printed VTK warnings/errors:\n" + "\n".join(bad) + f"\n---\n{text}"


def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(f"required under CI=true: {reason}")
    pytest.skip(reason)


@dataclass
class ParaView:
    """The installed ParaView and the environment for its Python."""

    pvpython: Path
    pvbatch: Path
    env: dict

    @staticmethod
    def call(cmd, **kwargs):
        """``subprocess.run(cmd, **kwargs)`` for pvpython/pvbatch, once more after an X crash.

        Debian's ParaView 5.11 aborts at start-up with "bad X server connection" when the X
        server refuses it; a private Xvfb no longer resets between clients (``-noreset``, the
        cause of about 1 abort in 20 launches), so this retry is only a safety net for a
        ``$DISPLAY`` given from outside.  Any other failure is returned as it is.
        """
        proc = subprocess.run(cmd, **kwargs)
        text = f"{proc.stdout or ''}{proc.stderr or ''}"
        if proc.returncode < 0 and "bad X server connection" in text:
            proc = subprocess.run(cmd, **kwargs)
        return proc

    def run(self, code: str, tmp_path: Path, *, env: dict | None = None, timeout: float = 300):
        """Run ``code`` in pvpython; return the CompletedProcess (stderr merged into stdout)."""
        script = tmp_path / "pv_script.py"
        script.write_text(code, encoding="utf-8")
        return self.call(
            [str(self.pvpython), str(script)],
            env=env or self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=timeout,
            check=False,
            cwd=tmp_path,
        )

    def cases(self, code: str, tmp_path: Path, volume: Path) -> dict:
        """Run a bad-input script (``@@CASE name`` ... ``@@END name ok=...`` blocks, then
        ``@@SURVIVED``) in pvpython on ``volume``; return each case's output by name."""
        script = tmp_path / "cases.py"
        script.write_text(code, encoding="utf-8")
        proc = self.call(
            [str(self.pvpython), str(script), str(volume)],
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=300,
            check=False,
        )
        text = proc.stdout
        assert proc.returncode == 0, text
        assert "@@SURVIVED" in text, text
        out = {}
        for chunk in text.split("@@CASE ")[1:]:
            name, _, body = chunk.partition("\n")
            out[name.strip()] = body
        return out

    @staticmethod
    def assert_errors(cases: dict, expected: dict) -> None:
        """Each named case failed (``ok=False``) with its message and no traceback."""
        for name, message in expected.items():
            assert message in cases[name], f"{name}:\n{cases[name]}"
            assert f"@@END {name} ok=False" in cases[name]
            assert "Traceback" not in cases[name], cases[name]

    @staticmethod
    def result(proc, *, clean: bool = True) -> dict:
        """The JSON object the script printed after :data:`MARK` (fails with the output).

        ``clean``: also fail if the run printed a VTK warning or error
        (:func:`assert_no_vtk_messages`).
        """
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(MARK)]
        assert proc.returncode == 0, f"pvpython failed ({proc.returncode}):\n{proc.stdout}"
        assert lines, f"pvpython printed no result:\n{proc.stdout}"
        if clean:
            assert_no_vtk_messages(f"{proc.stdout}{proc.stderr or ''}")
        return json.loads(lines[-1][len(MARK) :])


#: Scripts that ParaView runs (``paraview --script``): they import ``paraview``, so pytest's
#: doctest collection must not import them in the venv.
collect_ignore = ["view_actions_scene.py"]


@pytest.fixture(scope="session", autouse=True)
def _private_paraview_settings(tmp_path_factory):
    """ParaView keeps imported presets and macros in ``$XDG_CONFIG_HOME/ParaView``: the tests'
    ParaView runs (``pvbatch`` through the CLI too) get a folder of their own, never the user's."""
    old = os.environ.get("XDG_CONFIG_HOME")
    os.environ["XDG_CONFIG_HOME"] = str(tmp_path_factory.mktemp("paraview-config"))
    yield
    if old is None:
        os.environ.pop("XDG_CONFIG_HOME", None)
    else:
        os.environ["XDG_CONFIG_HOME"] = old


@pytest.fixture(scope="session")
def paraview() -> ParaView:
    """The ParaView installation; skips locally / fails under CI when it is missing."""
    from dvr_perception.cli.pvbatch import find_paraview, paraview_env
    from dvr_perception.errors import DVRInputError

    try:
        pvpython, pvbatch = find_paraview("pvpython"), find_paraview("pvbatch")
        env = paraview_env()
    except DVRInputError as exc:
        _missing(str(exc))
    return ParaView(pvpython, pvbatch, env)


@pytest.fixture(scope="module")
def mpiexec(paraview):
    """ParaView, with Open MPI's ``mpiexec`` (a failure under CI=true when missing)."""
    import shutil

    if shutil.which("mpiexec") is None:
        if IN_CI:
            pytest.fail("required under CI=true: mpiexec (openmpi-bin, make paraview-system)")
        pytest.skip("no mpiexec (apt-get install openmpi-bin)")
    return paraview


@pytest.fixture(scope="module")
def display():
    """An X display for ParaView (``$DISPLAY`` or a private Xvfb for the module)."""
    from dvr_perception.cli.pvbatch import virtual_display
    from dvr_perception.errors import DVRInputError

    try:
        with virtual_display() as d:
            yield d
    except DVRInputError as exc:  # the ``paraview`` fixture's policy: skip locally, fail in CI
        _missing(str(exc))


@pytest.fixture(scope="module")
def loopback_shim(tmp_path_factory) -> Path:
    """``loopback_bind.c`` built into a shared library for ``LD_PRELOAD``."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        _missing("a C compiler (cc) to build the loopback bind shim for pvserver")
    out = tmp_path_factory.mktemp("shim") / "libloopback_bind.so"
    src = Path(__file__).with_name("loopback_bind.c")
    cmd = [cc, "-shared", "-fPIC", "-O2", "-o", str(out), str(src), "-ldl"]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    return out
