"""Client/server: the plugin's filters run inside ``pvserver``, the client only fetches E_v.

A ``pvserver`` on a free port of this machine (under a private Xvfb) receives the plugin with
``LoadPlugin(path, remote=True)``; pvpython connects with ``Connect("localhost", port)``, reads
a shared volume on the server, runs *Perception Measures* there and fetches the (small)
output.  The server is stopped in every case.

pvserver 5.11 cannot be told which address to bind (``--hostname`` only names the host in the
connection URL) and listens on 0.0.0.0, plus OpenMPI's listener on 0.0.0.0 and [::].  The test
preloads ``loopback_bind.c`` (built here with ``cc``), which turns those wildcard binds into
127.0.0.1 / ::1, and checks in ``/proc/PID/net/tcp*`` that every socket pvserver listens on is
a loopback one before the client connects.
"""

from __future__ import annotations

import ipaddress
import os
import queue
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from dvr_perception.cli.pvbatch import find_paraview
from dvr_perception.errors import DVRInputError
from tests.plugin.conftest import CROSS_ENV_ABS

REPO = Path(__file__).resolve().parents[2]
PLUGIN = REPO / "dvr_perception" / "paraview" / "dvr_perception_plugin.py"
SPEC = REPO / "state_files" / "neghip.json"
SIZE = 32
MARK = "@@RESULT@@ "
START_TIMEOUT = 60.0  # seconds for pvserver to accept connections

CLIENT = f"""
import json, os, sys
from paraview.simple import *
from paraview import servermanager

port, volume = int(sys.argv[1]), sys.argv[2]
Connect("localhost", port)
conn = servermanager.ActiveConnection
LoadPlugin({str(PLUGIN)!r}, remote=True, ns=globals())
reader = NrrdReader(FileName=volume)
pm = PerceptionMeasures(Input=reader, SpecFile={str(SPEC)!r}, Width={SIZE}, Height={SIZE})
pm.UpdatePipeline()
info = pm.GetDataInformation()
e_v_info = pm.FieldData["E_v"].GetRange() if "E_v" in pm.FieldData.keys() else None
image = servermanager.Fetch(pm)
fd = image.GetFieldData()
print({MARK!r} + json.dumps({{
    "remote": bool(conn.IsRemote()),
    "client_pid": os.getpid(),
    "client_side_filter": pm.GetClientSideObject() is not None,
    "client_side_reader": reader.GetClientSideObject() is not None,
    "dims": list(info.GetExtent()),
    "points": info.GetNumberOfPoints(),
    "E_v_info": list(e_v_info) if e_v_info else None,
    "E": {{k: fd.GetArray(k).GetValue(0) if fd.GetArray(k) else None
          for k in ("E_v", "E_s", "E_t")}},
    "fetched_dims": list(image.GetDimensions()),
}}), flush=True)
Disconnect()
"""


def _listening(pid: int) -> list[tuple[str, int]]:
    """``(address, port)`` of every TCP socket process ``pid`` listens on (IPv4 and IPv6)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:[") : -1])
    found = []
    for table in ("tcp", "tcp6"):
        lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        for line in lines:
            fields = line.split()
            local, state, inode = fields[1], fields[3], fields[9]
            if state != "0A" or inode not in inodes:  # 0A: LISTEN
                continue
            hex_addr, hex_port = local.split(":")
            raw = bytes.fromhex(hex_addr)
            # /proc prints each 32-bit word in host (little-endian) order
            raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            found.append((str(ipaddress.ip_address(raw)), int(hex_port, 16)))
    return found


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _reader(stream, lines: queue.Queue) -> None:
    for line in stream:
        lines.put(line)
    lines.put(None)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def _library_e(shared_data):
    from dvr_perception.measures import shape, transparency, visibility
    from dvr_perception.rays.camera import Camera
    from dvr_perception.rays.curvature import curvature_volume
    from dvr_perception.rays.engine import analyze
    from dvr_perception.structures.io import load_spec
    from dvr_perception.volume import load_volume

    vol, spec = load_volume(shared_data / "neghip.nhdr"), load_spec(SPEC)
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    cam = Camera.from_view(vol.bounds, azimuth=az, elevation=el, zoom=zoom, width=SIZE, height=SIZE)
    curv, _ = curvature_volume(vol, spec, sigma=1.0)
    result = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    return {
        "E_v": visibility(result, spec).E_v,
        "E_s": shape(result, spec).E_s,
        "E_t": transparency(result, spec).E_t,
    }


def test_perception_measures_run_on_pvserver(
    paraview, display, loopback_shim, shared_data, tmp_path
):
    try:
        pvserver = find_paraview("pvserver")
    except DVRInputError as exc:
        pytest.fail(f"pvpython is installed but pvserver is not: {exc}")
    env = dict(paraview.env, DISPLAY=display)
    server_env = dict(env, LD_PRELOAD=str(loopback_shim))
    port = _free_port()
    cmd = [str(pvserver), f"--server-port={port}", "--hostname=localhost", "--timeout=5"]
    server = subprocess.Popen(
        cmd,
        env=server_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
    )
    lines: queue.Queue = queue.Queue()
    pump = threading.Thread(target=_reader, args=(server.stdout, lines), daemon=True)
    pump.start()
    log: list[str] = []
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not any("Accepting connection" in ln for ln in log):
            left = deadline - time.monotonic()
            assert left > 0, f"pvserver did not accept connections in {START_TIMEOUT} s:\n{log}"
            try:
                line = lines.get(timeout=left)
            except queue.Empty:
                continue
            assert line is not None, f"pvserver exited ({server.poll()}):\n{''.join(log)}"
            log.append(line)
        assert f":{port}" in "".join(log)
        # reachable from this machine only: every listening socket of pvserver is loopback
        sockets = _listening(server.pid)
        assert (("127.0.0.1", port)) in sockets, sockets
        assert all(ipaddress.ip_address(a).is_loopback for a, _ in sockets), sockets
        script = tmp_path / "client.py"
        script.write_text(CLIENT, encoding="utf-8")
        client = paraview.call(
            [str(paraview.pvpython), str(script), str(port), str(shared_data / "neghip.nhdr")],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=180,
            check=False,
            cwd=tmp_path,
        )
        got = paraview.result(client)
    finally:
        _stop(server)
        pump.join(timeout=10)
        server.stdout.close()
    while not lines.empty():
        line = lines.get()
        if line is not None:
            log.append(line)
    server_log = "".join(log)
    assert got["remote"], "the client's session is not a remote connection"
    # the pipeline lives on the server: the client holds no VTK objects for reader or filter
    assert not got["client_side_filter"]
    assert not got["client_side_reader"]
    assert got["dims"] == [0, SIZE - 1, 0, SIZE - 1, 0, 0]
    assert got["points"] == SIZE * SIZE
    assert got["fetched_dims"] == [SIZE, SIZE, 1]
    expected = _library_e(shared_data)
    for k in ("E_v", "E_s", "E_t"):
        assert got["E"][k] == pytest.approx(expected[k], abs=CROSS_ENV_ABS), k
    # the data information gathered from the server carries the same E_v
    assert got["E_v_info"] == pytest.approx([expected["E_v"]] * 2, abs=CROSS_ENV_ABS)
    assert "Client connected" in server_log, server_log
    assert server.returncode is not None  # stopped
