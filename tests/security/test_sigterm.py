"""SIGTERM cleans up as Ctrl-C does: no lock, no staging folder, no partial output (issue 29).

Without a handler SIGTERM ends the process at once, leaving the output folder's lock file and
an empty staging folder behind.  The command line raises it as
:class:`~dvr_perception._files.Terminated` (a ``KeyboardInterrupt``), so the clean-up of
:func:`~dvr_perception._files.output_folder` runs, and exits 143 (128 + 15, as shells report a
process SIGTERM ended) with one line ``dvr-perception: error: terminated``.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from dvr_perception import _files
from dvr_perception._files import (
    LOCK_NAME,
    Terminated,
    file_lock,
    output_folder,
    terminate_as_interrupt,
)
from dvr_perception.cli.measure import FIGURES

TERMINATED = 128 + signal.SIGTERM


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def _stage_then_terminate(out: Path, names, *, twice: bool = False) -> None:
    """Stage ``names`` in ``out``, then SIGTERM (and another during the clean-up)."""
    with output_folder(out) as staged:
        for name in names:
            (staged.path / name).write_text("new")
        assert (out / LOCK_NAME).exists()
        try:
            signal.raise_signal(signal.SIGTERM)
            time.sleep(0.05)
            pytest.fail("SIGTERM did not interrupt the block")
        finally:
            if twice:
                os.kill(os.getpid(), signal.SIGTERM)  # the handler fires once only
                time.sleep(0.05)


def _stage(out: Path, names) -> None:
    with output_folder(out) as staged:
        for name in names:
            (staged.path / name).write_text("new")


def _hold_then_terminate(target: Path) -> None:
    with file_lock(target) as lock:
        assert lock.exists()
        signal.raise_signal(signal.SIGTERM)
        time.sleep(0.05)


@pytest.mark.parametrize("twice", [False, True])
def test_sigterm_in_the_block_removes_staging_lock_and_created_folder(tmp_path, twice):
    out = tmp_path / "new"
    before = signal.getsignal(signal.SIGTERM)
    with terminate_as_interrupt(), pytest.raises(Terminated):
        _stage_then_terminate(out, ["a.png"], twice=twice)
    assert not out.exists()
    assert signal.getsignal(signal.SIGTERM) is before  # restored


def test_sigterm_leaves_an_existing_folder_as_it_was(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    with terminate_as_interrupt(), pytest.raises(Terminated):
        _stage_then_terminate(out, ["keep.txt", "b.png"])
    assert _names(out) == ["keep.txt"]
    assert (out / "keep.txt").read_text() == "old"


def test_sigterm_releases_a_file_lock(tmp_path):
    with terminate_as_interrupt(), pytest.raises(Terminated):
        _hold_then_terminate(tmp_path / "big.nhdr")
    assert _names(tmp_path) == []


def test_sigterm_during_the_renames_is_held_back(tmp_path, monkeypatch):
    """SIGTERM arriving between two renames is delivered after the last one: all files."""
    real = os.replace
    calls = []

    def replace_then_terminate(a, b):
        real(a, b)
        calls.append(b)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler runs here if it is not held back

    monkeypatch.setattr(_files.os, "replace", replace_then_terminate)
    out = tmp_path / "out"
    with terminate_as_interrupt(), pytest.raises(Terminated):
        _stage(out, ["a.png", "b.png", "c.json"])
    assert _names(out) == ["a.png", "b.png", "c.json"]
    assert len(calls) == 3


def _terminate(cli, argv, run: Path, out: Path, after_files: int):
    """Start ``argv``, wait for ``after_files`` staged files in ``out``, send SIGTERM."""
    proc = cli.start(argv, run)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        staging = [p for p in out.glob(".dvr-perception.staging-*") if p.is_dir()]
        if staging and len(list(staging[0].iterdir())) >= after_files:
            break
        time.sleep(0.005)
    sent = proc.poll() is None
    proc.send_signal(signal.SIGTERM)
    return cli.finish(proc), sent


@pytest.mark.parametrize("existing", [False, True], ids=["new-folder", "existing-folder"])
def test_sigterm_during_measure_leaves_nothing_partial(cli, tmp_path, existing):
    """SIGTERM while the analysis runs: exit 143, one line, the folder as it was before."""
    out = tmp_path / "m"
    if existing:
        out.mkdir()
        (out / "keep.txt").write_text("old")
    argv = ["measure", "phantom", "--size", "24", "--out-dir", out]
    result, sent = _terminate(cli, argv, tmp_path, out, 0)
    assert sent, result.stderr  # the run was still working when SIGTERM came
    assert result.code == TERMINATED, (result.code, result.stderr)
    assert result.stderr.strip().splitlines()[-1] == "dvr-perception: error: terminated"
    assert result.stdout == ""
    if existing:
        assert _names(out) == ["keep.txt"]
        assert (out / "keep.txt").read_text() == "old"
    else:
        assert not out.exists()
    assert _names(tmp_path) == (["m"] if existing else [])


def test_sigterm_while_figures_are_written_leaves_all_files_or_none(cli, tmp_path):
    out = tmp_path / "m"
    argv = ["measure", "phantom", "--size", "24", "--out-dir", out]
    result, _ = _terminate(cli, argv, tmp_path, out, 3)
    names = _names(out) if out.exists() else []
    assert names in ([], sorted(FIGURES)), (names, result.stderr)
    if names == []:
        assert result.code == TERMINATED, (result.code, result.stderr)
    else:  # it finished before the signal came, or the signal came during the commit
        assert result.code in (0, TERMINATED, -signal.SIGTERM), (result.code, result.stderr)


def _run_job_until_terminated(pidfile: Path) -> None:
    import threading

    from dvr_perception.cli.pvbatch import run_job

    def terminate_when_started():
        deadline = time.monotonic() + 30
        while not pidfile.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=terminate_when_started, daemon=True).start()
    cmd = ["sh", "-c", f"echo $$ > {pidfile}.tmp && mv {pidfile}.tmp {pidfile} && sleep 60"]
    run_job(cmd, dict(os.environ), 120, "job")


def test_sigterm_kills_the_pvbatch_job_group(tmp_path):
    """The job runs in a session of its own: SIGTERM to the command must not orphan it."""
    pidfile = tmp_path / "pid"
    t0 = time.monotonic()
    with terminate_as_interrupt(), pytest.raises(Terminated):
        _run_job_until_terminated(pidfile)
    assert time.monotonic() - t0 < 30
    pid = int(pidfile.read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # killed and reaped
