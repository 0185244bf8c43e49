"""Shared fixtures of the app tests, and the start of a real app server (a subprocess)."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvr_perception.app.session import PHANTOM, Session

#: A fresh clone compiles the numba kernels (cold cache) before the server listens.
START_TIMEOUT_S = 240
#: The line the server prints once it listens: the address to open, with its secret.
ADDRESS = re.compile(r"open (http://127\.0\.0\.1:\d+/\?secret=([\w-]+))")


@pytest.fixture
def session(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    s = Session(data, tmp_path / "exports", state_dir=tmp_path / "state", phantom_size=40)
    s.load_volume(PHANTOM)
    return s


def free_port() -> int:
    """Return a loopback port nobody listens on (now)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_app_server(root: Path, args: list[str]) -> dict:
    """Start ``dvr-perception app ARGS`` on a free loopback port; wait for its address.

    Returns ``{"proc", "port", "url", "token", "log"}``; ``url`` is the printed address (with
    the secret).  The caller stops ``proc``.
    """
    port = free_port()
    env = dict(os.environ)
    if not env.get("DISPLAY"):
        env["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    cmd = [sys.executable, "-c", "from dvr_perception.cli import main; raise SystemExit(main())"]
    cmd += ["app", "--port", str(port), "--host", "127.0.0.1", *args]
    log = root / "server.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=root)
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        m = ADDRESS.search(log.read_text())
        if m:
            return {"proc": proc, "port": port, "url": m.group(1), "token": m.group(2), "log": log}
        if proc.poll() is not None:
            pytest.fail(f"app server exited ({proc.returncode}):\n{log.read_text()[-3000:]}")
        time.sleep(0.3)
    stop_app_server(proc)
    pytest.fail(f"app server printed no address within {START_TIMEOUT_S} s:\n{log.read_text()}")


def stop_app_server(proc: subprocess.Popen) -> None:
    """Terminate the server started by :func:`start_app_server` (kill it after 10 s)."""
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


@pytest.fixture(scope="session")
def app_server():
    """The two functions that start and stop a real app server."""
    return start_app_server, stop_app_server
