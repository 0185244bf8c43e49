"""Run the command line in child processes and measure it (exit status, time, peak memory).

:func:`run_batch` runs the hostile cases in fresh interpreters and reads each call's peak
memory from the child's own ``VmHWM`` (``/proc/self/status``).  ``ru_maxrss`` is not used:
Linux carries the spawning process's peak into a child across fork and exec, so a child of a
large pytest process would report pytest's peak.  ``cli.start``/``cli.finish`` run one call
for the signal tests (exit status, output and time only).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import pytest

REPO = Path(__file__).resolve().parents[2]
#: Bounds every hostile input must meet (issue 18).
MAX_SECONDS = 10.0
MAX_RSS_MB = 400.0
KILL_AFTER = 60.0
_MAIN = "import sys; from dvr_perception.cli import main; sys.exit(main())"  # as the script


@dataclass
class Run:
    code: int
    seconds: float
    rss_mb: float
    stdout: str
    stderr: str

    def one_error(self, *needles: str) -> str:
        """Exit 2, one ``dvr-perception: error:`` line naming every needle, within bounds."""
        lines = self.stderr.strip().splitlines()
        assert self.code == 2, (self.code, self.stderr[-2000:])
        assert len(lines) == 1, self.stderr[-2000:]
        assert lines[0].startswith("dvr-perception: error: "), lines[0]
        assert len(lines[0]) < 600, lines[0]
        for needle in needles:
            assert needle in lines[0], (needle, lines[0])
        assert self.stdout == ""
        self.bounded()
        return lines[0]

    def bounded(self) -> None:
        assert self.seconds < MAX_SECONDS, self.seconds
        assert self.rss_mb < MAX_RSS_MB, self.rss_mb


def child_env(**extra) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.pop("DVR_PERCEPTION_DATA_ROOTS", None)
    env.update({k: str(v) for k, v in extra.items()})
    return env


def start_cli(argv, cwd: Path, **env) -> subprocess.Popen:
    out = open(cwd / ".stdout", "w+b")  # noqa: SIM115 - closed by finish()
    err = open(cwd / ".stderr", "w+b")  # noqa: SIM115
    proc = subprocess.Popen(
        [sys.executable, "-c", _MAIN, *map(str, argv)],
        cwd=cwd,
        env=child_env(**env),
        stdout=out,
        stderr=err,
        stdin=subprocess.DEVNULL,
    )
    proc._files = (out, err)  # type: ignore[attr-defined]
    proc._t0 = time.perf_counter()  # type: ignore[attr-defined]
    return proc


def finish(proc: subprocess.Popen) -> Run:
    timer = threading.Timer(KILL_AFTER, lambda: proc.send_signal(signal.SIGKILL))
    timer.start()
    try:
        _, status, _usage = os.wait4(proc.pid, 0)
    finally:
        timer.cancel()
    seconds = time.perf_counter() - proc._t0  # type: ignore[attr-defined]
    proc.returncode = os.waitstatus_to_exitcode(status)
    texts = []
    for f in proc._files:  # type: ignore[attr-defined]
        f.seek(0)
        texts.append(f.read().decode("utf-8", "replace"))
        f.close()
        Path(f.name).unlink()
    return Run(proc.returncode, seconds, math.nan, texts[0], texts[1])  # see the docstring


_BATCH = """
import io, json, os, resource, sys, time
from contextlib import redirect_stderr, redirect_stdout
from dvr_perception.cli import main
from dvr_perception.rays import memory
def peak_mb():
    # VmHWM: this process's own peak since exec (ru_maxrss would include the peak of the
    # process that spawned it, which the kernel carries across fork and exec)
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
cases = json.load(open(sys.argv[1]))
env0, cwd0, results = dict(os.environ), os.getcwd(), []
for case in cases:
    os.environ.clear()
    os.environ.update({**env0, **case["env"]})
    memory.set_limit(None)
    os.chdir(case["cwd"])
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(case["argv"])
    seconds = time.perf_counter() - t0
    rss = peak_mb()
    results.append([code, seconds, rss, out.getvalue(), err.getvalue()])
    os.chdir(cwd0)
json.dump(results, open(sys.argv[2], "w"))
"""


def run_batch(cases, folder: Path) -> list[Run]:
    """Run many CLI calls (``{"argv", "env", "cwd"[, "alone"]}``) in few child processes.

    The calls that fail early share one child: each result's ``rss_mb`` is that child's peak
    up to and including the call, an upper bound of the call's own peak, and ``seconds`` is
    the call's own time.  Calls marked ``alone`` (those that render: the engine keeps memos
    between calls of one process) get a child each.
    """
    results: dict[int, Run] = {}
    shared = [i for i, c in enumerate(cases) if not c.get("alone")]
    groups = [shared] + [[i] for i, c in enumerate(cases) if c.get("alone")]
    for n, group in enumerate(g for g in groups if g):
        runs = _run_group([cases[i] for i in group], folder, n)
        results.update(zip(group, runs, strict=True))
    return [results[i] for i in range(len(cases))]


def _run_group(cases, folder: Path, n: int) -> list[Run]:
    spec, out = folder / f"cases{n}.json", folder / f"results{n}.json"
    calls = [{"env": c.get("env", {}), "cwd": c["cwd"], "argv": [str(a) for a in c["argv"]]}
             for c in cases]  # fmt: skip
    spec.write_text(json.dumps(calls))
    proc = subprocess.Popen(
        [sys.executable, "-c", _BATCH, str(spec), str(out)],
        cwd=folder,
        env=child_env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    timer = threading.Timer(KILL_AFTER * 4, lambda: proc.send_signal(signal.SIGKILL))
    timer.start()
    try:
        err = proc.stderr.read().decode("utf-8", "replace")
        _, status, _usage = os.wait4(proc.pid, 0)
    finally:
        timer.cancel()
        proc.stderr.close()
    proc.returncode = os.waitstatus_to_exitcode(status)
    assert proc.returncode == 0, err[-3000:]
    return [Run(*r) for r in json.loads(out.read_text())]


@pytest.fixture
def cli():
    """``cli.run(argv, cwd, **env) -> Run``; ``cli.start``/``cli.finish`` for signals."""
    return SimpleNamespace(run=lambda argv, cwd, **env: finish(start_cli(argv, cwd, **env)),
                           start=start_cli, finish=finish)  # fmt: skip


@pytest.fixture(scope="session")
def batch():
    """:func:`run_batch`, for session fixtures."""
    return run_batch
