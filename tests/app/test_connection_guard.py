"""The app server's checks without a server: token, host, origin, chunk re-assembly."""

from __future__ import annotations

import struct

import msgpack
import pytest

from dvr_perception.app.security import (
    AUTH_MESSAGE_BYTES,
    BoundedUnChunker,
    ConnectionGuard,
    new_token,
)


def _chunks(obj, msg_id: int, size: int) -> list[bytes]:
    data = msgpack.packb(obj)
    return [
        struct.pack("<III", msg_id, off, len(data)) + data[off : off + size]
        for off in range(0, len(data), size)
    ]


def test_tokens_are_random_and_compared_whole():
    a, b = new_token(), new_token()
    assert a != b
    assert len(a) >= 43
    guard = ConnectionGuard(a, "127.0.0.1", 1000)
    assert guard.valid(a)
    assert not guard.valid(a[:-1])
    assert not guard.valid(b)
    assert not guard.valid(None)
    assert not guard.valid("wslink-secret")


@pytest.mark.parametrize(
    ("bound", "host", "allowed"),
    [
        ("127.0.0.1", "127.0.0.1:8080", True),
        ("127.0.0.1", "localhost:8080", True),
        ("127.0.0.1", "[::1]:8080", True),
        ("127.0.0.1", "evil.example:8080", False),  # DNS rebinding
        ("192.168.1.5", "192.168.1.5:8080", True),
        ("192.168.1.5", "evil.example:8080", False),
        ("0.0.0.0", "my-laptop.lan:8080", True),
        ("0.0.0.0", "", False),
        ("127.0.0.1", "127.0.0.1:port", False),
        ("127.0.0.1", "[::1", False),
    ],
)
def test_host_names_this_server(bound, host, allowed):
    assert ConnectionGuard("t", bound, 1000).host_allowed(host) is allowed


@pytest.mark.parametrize(
    ("origin", "allowed"),
    [
        ("http://127.0.0.1:8080", True),
        ("http://127.0.0.1:8081", False),
        ("https://127.0.0.1:8080", False),
        ("http://localhost:8080", False),
        ("null", False),
        (None, False),
    ],
)
def test_origin_is_the_page_itself(origin, allowed):
    guard = ConnectionGuard("t", "127.0.0.1", 1000)
    assert guard.origin_allowed(origin, "127.0.0.1:8080", "http") is allowed


def test_cookie_names_differ_per_port():
    assert ConnectionGuard.cookie_name("127.0.0.1:8080") != ConnectionGuard.cookie_name(
        "127.0.0.1:8081"
    )


def test_unchunker_reassembles_within_the_limit():
    refused = []
    u = BoundedUnChunker(10_000, refused.append)
    u.set_max_message_size(4 * 2**30)  # what wslink asks for after the hello
    assert u.max_message_size == 10_000
    message = {"method": "x", "args": ["a" * 3000]}
    parts = _chunks(message, 5, 1000)
    assert len(parts) > 2
    assert [u.process_chunk(p) for p in parts[:-1]] == [None] * (len(parts) - 1)
    assert u.process_chunk(parts[-1]) == message
    assert refused == []


def test_unchunker_before_the_hello_takes_small_messages_only():
    refused = []
    u = BoundedUnChunker(10_000, refused.append)
    assert u.max_message_size == AUTH_MESSAGE_BYTES
    assert u.process_chunk(struct.pack("<III", 1, 0, 2000) + b"x") is None
    assert "claiming 2000 bytes" in refused[0]


@pytest.mark.parametrize(
    "chunks",
    [
        [struct.pack("<III", 1, 0, 2**30) + bytes(10)],  # a claim above the limit
        [struct.pack("<III", k, 0, 3000) + b"x" for k in range(1, 5)],  # 12000 bytes under way
        [struct.pack("<III", 1, 0, 100) + b"x", struct.pack("<III", 1, 50, 100) + b"y"],  # gap
        [struct.pack("<III", 1, 0, 100) + b"x", struct.pack("<III", 1, 1, 200) + b"y"],  # resize
        [struct.pack("<III", 1, 0, 4) + b"toolong"],  # more than claimed
        [struct.pack("<III", 1, 0, 3) + b"\xc1\xc1\xc1"],  # not msgpack
        [b"short"],
    ],
)
def test_unchunker_refuses_and_stops(chunks):
    refused = []
    u = BoundedUnChunker(10_000, refused.append)
    u.set_max_message_size(10_000)
    for c in chunks:
        assert u.process_chunk(c) is None
    assert len(refused) == 1
    assert u.refused
    # once refused, nothing more is taken from that connection
    assert u.process_chunk(_chunks({"a": 1}, 9, 100)[0]) is None


def test_a_disconnect_traceback_becomes_one_line(caplog):
    import logging

    from dvr_perception.app.security import _STACK_LOGGERS, quiet_disconnects

    quiet_disconnects()
    quiet_disconnects()  # once is enough: no second filter
    try:
        gone = ConnectionResetError("Cannot write to closing transport")
        with caplog.at_level(logging.INFO):
            logging.getLogger("asyncio").error(
                "Task exception was never retrieved", exc_info=(type(gone), gone, None)
            )
            logging.getLogger("wslink.protocol").critical(
                "wslink is not expecting text message:\n> %s", "hello"
            )
            logging.getLogger("asyncio").error("something else")
        lines = [(r.name, r.getMessage(), r.exc_info) for r in caplog.records]
        assert lines == [
            (
                "dvr_perception.app",
                "a client disconnected abruptly (ConnectionResetError: Cannot write to closing "
                "transport)",
                None,
            ),
            ("dvr_perception.app", "websocket client refused: hello", None),
            ("asyncio", "something else", None),  # other errors pass unchanged
        ]
        assert all(len(logging.getLogger(n).filters) == 1 for n in _STACK_LOGGERS)
    finally:
        for name in _STACK_LOGGERS:
            for f in list(logging.getLogger(name).filters):
                logging.getLogger(name).removeFilter(f)
