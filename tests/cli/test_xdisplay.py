"""The private X display ParaView renders into (:mod:`dvr_perception.cli.xdisplay`).

A server on a random high display number that answers an X connection set-up before its
number is handed out; a number already served is skipped; the server is gone after the block.
"""

from __future__ import annotations

import os
import random
import shutil
import socket
import threading
from pathlib import Path

import pytest

from dvr_perception.cli import xdisplay
from dvr_perception.cli.xdisplay import DISPLAY_RANGE, display_answers, virtual_display
from dvr_perception.errors import DVRInputError
from tests.conftest import _missing


@pytest.fixture
def no_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    if shutil.which("Xvfb") is None:
        _missing("Xvfb (apt-get install xvfb; make paraview-setup)")


class _Draws(random.Random):
    """An rng whose ``randrange`` returns the given numbers in turn."""

    def __init__(self, numbers):
        super().__init__(0)
        self.numbers = list(numbers)

    def randrange(self, *_args):
        return self.numbers.pop(0)


def _fake_server(number: int, reply: bytes, got: list) -> socket.socket:
    """A one-shot server on ``:number``'s abstract socket that answers ``reply``."""
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(f"\0/tmp/.X11-unix/X{number}")
    server.listen(1)

    def serve():
        conn, _ = server.accept()
        with conn:
            got.append(conn.recv(12))
            conn.sendall(reply + b"\0" * 7)

    threading.Thread(target=serve, daemon=True).start()
    return server


@pytest.mark.parametrize(
    ("reply", "answers"), [(b"\x01", True), (b"\x00", False), (b"\x02", False)]
)
def test_display_answers_reads_the_set_up_status(reply, answers):
    got: list = []
    with _fake_server(29_917, reply, got):
        assert display_answers(":29917.0") is answers
    # the request: little-endian, protocol 11.0, no authorisation name or data
    assert got == [b"l\0\x0b\0\0\0\0\0\0\0\0\0"]


def test_display_answers_is_false_without_a_server():
    assert display_answers(29_916, timeout=1) is False


def test_a_private_display_answers_inside_the_block_only(no_display):
    with virtual_display(rng=random.Random(7)) as display:
        number = int(display[1:])
        assert DISPLAY_RANGE[0] <= number < DISPLAY_RANGE[1]
        assert display_answers(display)
        assert Path(f"/tmp/.X{number}-lock").exists()  # what xvfb-run -a looks for
    assert not display_answers(display, timeout=1)
    assert not Path(f"/tmp/.X{number}-lock").exists()


def test_a_number_already_served_is_skipped(no_display):
    with virtual_display(rng=random.Random(11)) as first:
        taken = int(first[1:])
        free = taken + 1 if taken + 1 < DISPLAY_RANGE[1] else taken - 1
        with virtual_display(rng=_Draws([taken, free])) as second:
            assert second == f":{free}"
            assert display_answers(first)
            assert display_answers(second)


def test_an_existing_display_is_used_as_it_is(monkeypatch):
    monkeypatch.setenv("DISPLAY", ":42")
    with virtual_display() as display:
        assert display == ":42"


def test_without_xvfb_one_error_names_it(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(shutil, "which", lambda _name: None)
    with pytest.raises(DVRInputError, match="Xvfb is not installed"), virtual_display():
        pass


def test_when_no_server_starts_the_error_lists_the_numbers(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(shutil, "which", lambda _name: "/usr/bin/Xvfb")
    monkeypatch.setattr(xdisplay, "_start", lambda *_a: None)
    numbers = list(range(300, 300 + xdisplay.START_ATTEMPTS))
    expected = r"none of the displays :300, :301, .*:307"
    with pytest.raises(DVRInputError, match=expected), virtual_display(rng=_Draws(numbers)):
        pass
    assert os.environ.get("DISPLAY") is None


def test_the_server_answers_every_client_that_follows_a_closed_one(no_display):
    """No reset after the last client leaves: a server that resets refuses some of these
    (1-2 in 100 here, the "bad X server connection" of ParaView's start-up)."""
    with virtual_display(rng=random.Random(5)) as display:
        refused = sum(not display_answers(display, timeout=2) for _ in range(500))
    assert refused == 0
