"""Hostile clients of the web app (issue 18): a real server on 127.0.0.1, real websockets.

The server (``dvr-perception app``, 16-voxel phantom) gets a read-only data folder and a state
folder; next to them lies an ``outside`` folder with a spec whose structure is called
:data:`SECRET`.  The clients are aiohttp's websocket client speaking wslink/trame, and raw
sockets for what no polite client sends (a frame claiming 1 GiB).  The tests run in file
order; the last one reads the server's whole log.
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import http.client
import itertools
import json
import os
import re
import socket
import struct
import time
import zlib
from pathlib import Path

import msgpack
import pytest

aiohttp = pytest.importorskip("aiohttp")

pytestmark = [pytest.mark.vtk_render, pytest.mark.slow]

MAX_UPLOAD_MB = 4
#: Most the server's resident memory may grow under one attack.
RSS_GROWTH_MB = 100
COOKIE = "dvr_perception_token_{port}"
#: Name of the structure in the spec outside the data folder: must never reach a client.
SECRET = "SECRETSTRUCTURE"
GIB = 2**30


# -- the server ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def server(tmp_path_factory, vtk_can_render, app_server):
    from dvr_perception.structures import make_phantom, save_spec

    root = tmp_path_factory.mktemp("hostile")
    data, outside = root / "data", root / "outside"
    data.mkdir()
    outside.mkdir()
    _, spec = make_phantom(size=16)
    secret = dataclasses.replace(spec.structures[0], name=SECRET)
    save_spec(
        dataclasses.replace(spec, structures=(secret, *spec.structures[1:])), outside / "s.json"
    )
    (outside / "secret.raw").write_bytes(b"S" * 4096)
    (outside / "answers.csv").write_text("kept as it is\n", encoding="utf-8")
    start, stop = app_server
    args = ["--data-dir", str(data), "--state-dir", str(root / "state")]
    args += ["--phantom-size", "16", "--max-upload-mb", str(MAX_UPLOAD_MB), "--iterations", "2"]
    data.chmod(0o555)
    try:
        srv = start(root, args)
        try:
            yield {**srv, "root": root, "data": data, "outside": outside, "state": root / "state"}
        finally:
            stop(srv["proc"])
    finally:
        data.chmod(0o755)


def _status_mb(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no {field} for process {pid}")


def _start_peak(pid: int) -> float:
    """Reset the process's peak RSS (VmHWM) to its RSS now; return that RSS, in MB."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    return _status_mb(pid, "VmRSS")


def _peak_growth(pid: int, rss0: float) -> float:
    """How far the RSS rose above ``rss0`` at its peak since :func:`_start_peak`, in MB."""
    return max(_status_mb(pid, "VmHWM"), _status_mb(pid, "VmRSS")) - rss0


def _files_outside_the_state_folder(root: Path) -> dict:
    """Every file under ``root`` except the app's state folder and the server log."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_relative_to(root / "state") or p.name == "server.log":
            continue
        st = p.lstat()
        out[str(p.relative_to(root))] = (st.st_size, st.st_mtime_ns, p.is_dir())
    return out


# -- raw HTTP and websocket ----------------------------------------------------------------------
def _get(port: int, path: str, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request("GET", path, headers=headers or {})
        r = conn.getresponse()
        return r.status, r.headers, r.read()
    finally:
        conn.close()


def _handshake(port: int, *, token=None, origin="own", host=None):
    """Open a raw websocket handshake; return ``(socket, status line)``."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    own = f"http://127.0.0.1:{port}"
    lines = [
        "GET /ws HTTP/1.1",
        f"Host: {host or f'127.0.0.1:{port}'}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}",
        "Sec-WebSocket-Version: 13",
    ]
    if origin is not None:
        lines.append(f"Origin: {own if origin == 'own' else origin}")
    if token is not None:
        lines.append(f"Cookie: {COOKIE.format(port=port)}={token}")
    sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk:
            break
        head += chunk
    return sock, head.split(b"\r\n")[0].decode()


def _frame(payload: bytes, *, claimed: int | None = None, opcode: int = 0x2) -> bytes:
    """One masked client frame (binary); ``claimed`` overrides the length in its header."""
    n = len(payload) if claimed is None else claimed
    head = bytes([0x80 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 65536:
        head += bytes([0x80 | 126]) + struct.pack(">H", n)
    else:
        head += bytes([0x80 | 127]) + struct.pack(">Q", n)
    mask = os.urandom(4)
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def _chunk(obj, msg_id: int = 1, *, claimed: int | None = None) -> bytes:
    """A whole wslink message as one chunk (12-byte header: id, offset, total size)."""
    data = msgpack.packb(obj)
    return struct.pack("<III", msg_id, 0, len(data) if claimed is None else claimed) + data


def _hello(secret: str) -> dict:
    return {
        "wslink": "1.0",
        "id": "system:c0:0",
        "method": "wslink.hello",
        "args": [{"secret": secret}],
    }


def _close_code(sock: socket.socket) -> int | None:
    """Read server frames until a close frame; return its code (``None``: connection dropped)."""
    buf = b""

    def take(n: int) -> bytes:
        nonlocal buf
        while len(buf) < n:
            data = sock.recv(65536)
            if not data:
                raise EOFError
            buf += data
        out, buf = buf[:n], buf[n:]
        return out

    try:
        while True:
            b0, b1 = take(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", take(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", take(8))[0]
            payload = take(n)
            if b0 & 0x0F == 0x8:
                return struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 1005
    except (EOFError, ConnectionError, TimeoutError):
        return None


# -- a wslink/trame client on aiohttp -------------------------------------------------------------
class Client:
    """Speak trame's protocol over aiohttp's websocket client; keep every message received."""

    def __init__(self, ws) -> None:
        self.ws = ws
        self.ids = itertools.count(1)
        self.received: list = []
        self.client_id = "c0"

    async def send(self, obj, *, frame_bytes: int = 2**20) -> None:
        data = msgpack.packb(obj)
        msg_id = int.from_bytes(os.urandom(4), "little")
        for offset in range(0, len(data), frame_bytes):
            head = struct.pack("<III", msg_id, offset, len(data))
            await self.ws.send_bytes(head + data[offset : offset + frame_bytes])

    async def call(self, method: str, args, *, timeout: float = 120):
        rpc = f"rpc:{self.client_id}:{next(self.ids)}"
        if method == "wslink.hello":
            rpc = "system:c0:0"
        await self.send({"wslink": "1.0", "id": rpc, "method": method, "args": args, "kwargs": {}})
        parts: dict = {}
        while True:
            msg = await self.ws.receive(timeout=timeout)
            if msg.type != aiohttp.WSMsgType.BINARY:
                raise ConnectionError(f"websocket ended: {msg.type} {msg.data} {msg.extra}")
            msg_id, _, total = struct.unpack_from("<III", msg.data)
            buf = parts.setdefault(msg_id, bytearray())
            buf += msg.data[12:]
            if len(buf) < total:
                continue
            reply = msgpack.unpackb(bytes(parts.pop(msg_id)))
            self.received.append(reply)
            if reply.get("id") == rpc:
                return reply

    async def hello(self, secret: str) -> dict:
        reply = await self.call("wslink.hello", [{"secret": secret}])
        if "result" in reply:
            self.client_id = reply["result"]["clientID"]
        return reply

    async def update(self, **changes) -> dict:
        return await self.call(
            "trame.state.update", [[{"key": k, "value": v} for k, v in changes.items()]]
        )

    async def state(self) -> dict:
        return (await self.call("trame.state.get", []))["result"]["state"]

    async def trigger(self, element_id: str, *args) -> dict:
        template = (await self.state())["trame__template_main"]
        m = re.search(rf"id=\"{element_id}\"[^>]*?trigger\('(\w+)'", template)
        assert m, f"no trigger on #{element_id}"
        return await self.call("trame.trigger", [m.group(1), list(args), {}])

    def text(self) -> str:
        """Everything received, as text (bytes shown by their repr)."""
        return json.dumps(self.received, default=repr)


async def _open(session, srv, *, secret: str | None = None) -> Client:
    base = f"http://127.0.0.1:{srv['port']}"
    ws = await session.ws_connect(
        f"{base}/ws",
        headers={"Origin": base, "Cookie": f"{COOKIE.format(port=srv['port'])}={srv['token']}"},
    )
    client = Client(ws)
    reply = await client.hello(srv["token"] if secret is None else secret)
    if secret is None:
        assert "result" in reply, reply
    return client


def _run(coro):
    return asyncio.run(coro)


# -- the tests ------------------------------------------------------------------------------------
def test_the_page_needs_the_printed_token(server):
    port, token = server["port"], server["token"]
    cookie_name = COOKIE.format(port=port)
    assert server["url"] == f"http://127.0.0.1:{port}/?secret={token}"
    assert len(token) >= 40
    assert _get(port, "/")[0] == 403
    assert _get(port, "/index.html?secret=wrong")[0] == 403
    assert _get(port, "/index.html?secret=wslink-secret")[0] == 403
    status, headers, body = _get(port, f"/index.html?secret={token}")
    assert status == 200
    assert b"<html" in body.lower()
    cookie = headers["Set-Cookie"]
    assert f"{cookie_name}={token}" in cookie
    assert "HttpOnly" in cookie
    assert "SameSite=Strict" in cookie
    # a reload (cookie, no secret in the address) gets the secret back for the page's websocket
    status, headers, _ = _get(port, "/index.html", {"Cookie": f"{cookie_name}={token}"})
    assert status == 302
    assert headers["Location"].endswith(f"?secret={token}")
    # a DNS-rebinding page (another host name for 127.0.0.1) is refused even with the token
    assert _get(port, f"/index.html?secret={token}", {"Host": f"evil.example:{port}"})[0] == 403
    assert _get(port, f"/index.html?secret={token}", {"Host": "127.0.0.1:no-port"})[0] == 403


@pytest.mark.parametrize(
    ("origin", "with_token"),
    [
        ("http://evil.example", True),
        ("null", True),
        (None, True),
        ("http://localhost:{port}", True),  # another origin, though the same machine
        ("own", False),
    ],
)
def test_a_foreign_or_tokenless_websocket_is_refused(server, origin, with_token):
    port = server["port"]
    if origin and "{port}" in origin:
        origin = origin.format(port=port)
    token = server["token"] if with_token else None
    sock, status = _handshake(port, token=token, origin=origin)
    sock.close()
    assert status.split()[1] == "403", status
    sock, status = _handshake(port, token=server["token"])  # the app's own page is let in
    sock.close()
    assert status.split()[1] == "101", status


def test_aiohttp_client_from_another_origin_is_refused(server):
    async def attempt():
        async with aiohttp.ClientSession() as session:
            with pytest.raises(aiohttp.WSServerHandshakeError) as info:
                await session.ws_connect(
                    f"http://127.0.0.1:{server['port']}/ws",
                    headers={
                        "Origin": "http://evil.example",
                        "Cookie": f"{COOKIE.format(port=server['port'])}={server['token']}",
                    },
                )
            return info.value.status

    assert _run(attempt()) == 403


def test_the_default_wslink_secret_does_not_authenticate(server):
    async def attempt():
        async with aiohttp.ClientSession() as session:
            client = await _open(session, server, secret="wslink-secret")
            refused = client.received[-1]
            update = await client.update(rank_file="/tmp/x.csv")
            await client.ws.close()
            return refused, update

    refused, update = _run(attempt())
    assert refused["error"]["message"] == "Authentication failed"
    assert "Unauthorized" in update["error"]["message"]


def test_no_client_message_reads_or_writes_outside_the_app_folders(server):
    root, outside, state = server["root"], server["outside"], server["state"]
    before = _files_outside_the_state_folder(root)
    targets = ["../outside/s.json", str(outside / "s.json"), "saved/../../outside/s.json"]
    targets += ["../../outside/s.json", "/etc/passwd", "s.json"]

    async def attack():
        async with aiohttp.ClientSession() as session:
            c = await _open(session, server)
            # the path variables of the probe: the server must not use them
            await c.update(
                rank_file=str(outside / "answers.csv"),
                spec_path=str(outside / "s.json"),
                cal_file=str(outside / "cal.json"),
                export_dir=str(outside),
                data_dir=str(outside),
                export_dir_label=str(outside),
                state_dir_label=str(outside),
            )
            errors = {}
            for name in targets:
                await c.update(spec_name=name)
                await c.trigger("load-spec", name)
                errors[("load", name)] = (await c.state())["error"]
                await c.trigger("save-spec", name)
                errors[("save", name)] = (await c.state())["error"]
            for name in ("../outside/s.json", "/etc/passwd", "uploaded/../../outside/x.nrrd"):
                await c.update(volume_name=name)
                errors[("volume", name)] = (await c.state())["error"]
            await c.update(cal_name="../outside/cal.json")
            await c.trigger("cal-load")
            errors[("calibration", "")] = (await c.state())["error"]
            # a NRRD whose header names a data file outside (relative to the uploads folder)
            nrrd = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 16 16 16\nencoding: raw\n"
            nrrd += b"data file: ../../outside/secret.raw\n\n"
            await c.update(upload={"name": "x.nrrd", "size": len(nrrd), "content": nrrd})
            errors[("upload", "")] = (await c.state())["error"]
            # the writes the app does make land in its own folders
            await c.update(error="")
            await c.trigger("export")
            await c.trigger("rank-new")
            for _ in range(600):
                st = await c.state()
                if st["rank_images"] and not st["rank_busy"]:
                    break
                await asyncio.sleep(0.2)
            order = [img["id"] for img in st["rank_images"]]
            await c.trigger("rank-save", order)
            final = await c.state()
            await c.ws.close()
            return errors, final, c.text()

    errors, final, received = _run(attack())
    assert errors.pop(("save", "s.json")) == ""  # a plain name: saved in the app's folder
    assert (state / "settings" / "s.json").is_file()
    for (what, name), error in errors.items():
        assert error, f"{what} {name!r} was accepted"
        if what == "load":
            assert "not one of the settings files offered" in error
        if what == "save":
            assert "plain file name" in error
        if what == "volume":
            assert "not one of the volumes offered" in error
    assert "detached data file" in errors[("upload", "")]
    assert "4096" not in errors[("upload", "")]  # nothing said about the file it named
    assert final["error"] == "", final["error"]
    assert "agrees on" in final["rank_result"]
    assert SECRET not in received
    assert "SSSS" not in received
    assert _files_outside_the_state_folder(root) == before  # nothing created, appended, touched
    assert (outside / "answers.csv").read_text(encoding="utf-8") == "kept as it is\n"
    assert (state / "exports" / "ranking_answers.csv").is_file()
    assert (state / "exports" / "phantom_spec.json").is_file()
    assert not (state / "uploads").exists() or not any((state / "uploads").iterdir())


def _gzip_bomb(claimed_sizes: str) -> bytes:
    """A NRRD of 1 GiB of zeros, gzip-compressed to about 1 MB, under a header of ``sizes``."""
    head = f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {claimed_sizes}\nencoding: gzip\n\n"
    packer = zlib.compressobj(9, zlib.DEFLATED, 31)
    zeros = bytes(2**20)
    body = b"".join(packer.compress(zeros) for _ in range(1024)) + packer.flush()
    return head.encode() + body


@pytest.mark.parametrize(
    ("sizes", "message"),
    [("64 64 64", "expands beyond"), ("1024 1024 1024", "more than the limit")],
)
def test_a_gzip_bomb_upload_is_refused_with_bounded_memory(server, sizes, message):
    bomb = _gzip_bomb(sizes)
    assert len(bomb) < MAX_UPLOAD_MB * 1e6  # small enough to be accepted as an upload

    async def attack():
        async with aiohttp.ClientSession() as session:
            c = await _open(session, server)
            await c.update(error="")
            rss0 = _start_peak(server["proc"].pid)
            await c.update(upload={"name": "bomb.nrrd", "size": len(bomb), "content": bomb})
            error = (await c.state())["error"]
            grown = _peak_growth(server["proc"].pid, rss0)
            await c.ws.close()
            return error, grown

    error, grown = _run(attack())
    print(f"gzip bomb ({sizes}): peak RSS grew by {grown:.1f} MB")
    assert grown < RSS_GROWTH_MB, f"RSS grew by {grown:.0f} MB"
    assert message in error
    uploads = server["state"] / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())


@pytest.mark.parametrize("kind", ["frame", "chunk", "chunk before hello"])
def test_a_huge_claimed_message_is_refused_with_bounded_memory(server, kind):
    pid, port, token = server["proc"].pid, server["port"], server["token"]
    rss0 = _start_peak(pid)
    sock, status = _handshake(port, token=token)
    assert status.split()[1] == "101"
    if kind != "chunk before hello":
        sock.sendall(_frame(_chunk(_hello(token))))
    if kind == "frame":  # 22 bytes: a frame header claiming 1 GiB, then 8 bytes
        attack = _frame(bytes(8), claimed=GIB)
        assert len(attack) == 22
    else:  # a wslink chunk header claiming a 1 GiB message
        attack = _frame(struct.pack("<III", 7, 0, GIB) + bytes(10))
    sock.sendall(attack)
    time.sleep(1.0)  # whatever the server allocates for the claim, it holds it now
    grown = _peak_growth(pid, rss0)
    code = _close_code(sock)
    sock.close()
    print(f"{kind} claiming 1 GiB: closed with {code}, peak RSS grew by {grown:.1f} MB")
    assert code == 1009  # "message too big"
    assert grown < RSS_GROWTH_MB
    assert server["proc"].poll() is None
    sock, status = _handshake(port, token=token)  # the server still serves
    sock.close()
    assert status.split()[1] == "101"


def test_abrupt_disconnects_and_every_refusal_log_one_line(server):
    port, token = server["port"], server["token"]
    hello = _frame(_chunk(_hello(token)))
    sock, _ = _handshake(port, token=token)
    sock.sendall(hello + _frame(b"plain text", opcode=0x1))  # wslink takes binary frames only
    time.sleep(0.5)
    sock.close()
    for k in range(30):  # clients gone while the server answers them (wslink logs a traceback)
        sock, _ = _handshake(port, token=token)
        update = {"wslink": "1.0", "id": "rpc:x:1", "method": "trame.state.update"}
        update["args"] = [[{"key": "show_map", "value": k % 2 == 0}]]
        get = {"wslink": "1.0", "id": "rpc:x:2", "method": "trame.state.get", "args": []}
        sock.sendall(hello + _frame(_chunk(update, 2)) + _frame(_chunk(get, 3)))
        time.sleep(0.05 * (k % 5))
        sock.close()
    time.sleep(3)
    assert server["proc"].poll() is None
    log = server["log"].read_text()
    assert "Traceback" not in log, log[-3000:]
    assert "websocket client refused: plain text" in log
    assert "wslink is not expecting" not in log  # its two-line message, made one line
    assert log.count("disconnected abruptly") <= 2  # one line, at most every 5 s
    refusals = [line for line in log.splitlines() if "refused" in line]
    assert any("origin 'http://evil.example'" in line for line in refusals)
    assert any("claiming 1073741824 bytes" in line for line in refusals)
    assert any("exceeds limit" in line for line in refusals)  # the 22-byte frame
    assert all(line.startswith("dvr-perception: ") for line in refusals)
