"""A private X display for Debian's ParaView, which renders only through X.

:func:`virtual_display` yields ``$DISPLAY`` when there is one, else starts ``Xvfb`` for the
block.  The display number is drawn at random from a high range instead of taking the lowest
free one (what ``xvfb-run -a`` and ``Xvfb -displayfd`` do): the lowest numbers are the ones other
jobs sharing ``/tmp`` reach for, and a server whose ``/tmp/.X0-lock`` belongs to a process
another job cannot see is taken over as stale.  Before the number is handed out the server must
answer an X connection set-up (:func:`display_answers`), the check a client's ``XOpenDisplay``
makes.  The server never resets (``-noreset``, see :data:`_SERVER_ARGS`).
"""

from __future__ import annotations

import os
import random
import shutil
import socket
import struct
import subprocess
import tempfile
import time
from contextlib import contextmanager

from dvr_perception.cli._common import log
from dvr_perception.errors import DVRInputError

__all__ = ["display_answers", "virtual_display"]

#: Display numbers tried for a private server: random ones from this range (``-nolisten tcp``,
#: so no TCP port is taken).
DISPLAY_RANGE = (200, 30000)
#: Servers started before giving up (a number in use makes Xvfb exit at once).
START_ATTEMPTS = 8
#: Seconds a new Xvfb may take to answer a connection set-up.
START_TIMEOUT = 30.0
#: ``-noreset``: by default an X server resets when its last client disconnects and refuses
#: the clients that connect meanwhile (measured here: 1-2 in 100 connections made right after
#: another closed).  ParaView's start-up, MPI ranks and the check below open and close
#: connections, so that reset was Debian's pvbatch aborting with "bad X server connection".
_SERVER_ARGS = ("-screen", "0", "1280x1024x24", "-nolisten", "tcp", "-noreset")


def _socket_names(number: int) -> list[str]:
    """Where a client connects for ``:number``: the abstract socket first, then the file."""
    path = f"/tmp/.X11-unix/X{number}"
    return [f"\0{path}", path]


def display_answers(display: str | int, *, timeout: float = 5.0) -> bool:
    """Whether the local X server of ``display`` accepts a connection set-up without a cookie.

    Sends the X11 connection set-up request (protocol 11.0, no authorisation) over the
    server's Unix socket, in the order libxcb tries them, and reads the status byte of the
    reply: 1 is success, 0 a refusal, 2 a request to authenticate.

    Parameters
    ----------
    display : str or int
        ``":N"``, ``":N.S"`` or the number ``N``.
    timeout : float, optional
        Seconds for the connection and the reply.

    Returns
    -------
    bool
        True when the server answered with success.

    Examples
    --------
    >>> display_answers(":29999")  # no server there
    False
    """
    text = str(display)
    number = int(text.lstrip(":").split(".")[0])
    for name in _socket_names(number):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout)
            try:
                sock.connect(name)
            except OSError:
                continue  # libxcb also moves on to the file socket
            try:
                sock.sendall(b"l\0" + struct.pack("<HHHH", 11, 0, 0, 0) + b"\0\0")
                status = sock.recv(1)
            except OSError:
                return False
            return status == b"\x01"
    return False


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _start(xvfb: str, number: int, errors) -> subprocess.Popen | None:
    """Xvfb on ``:number``, answering clients; None when it could not (``errors`` has why).

    A number with a lock file or a server is skipped.  No ``-displayfd``: with it Xvfb writes no
    ``/tmp/.X<N>-lock``, the file other programs (``xvfb-run -a``) look at to find a free
    number.  The server is ready when it answers.
    """
    if os.path.exists(f"/tmp/.X{number}-lock") or display_answers(number, timeout=2):
        errors.write(f"display :{number} is in use\n".encode())
        errors.flush()  # Xvfb writes to the same file
        return None  # served already: an answer below could come from that server
    cmd = [xvfb, f":{number}", *_SERVER_ARGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=errors)
    deadline = time.monotonic() + START_TIMEOUT
    while proc.poll() is None and time.monotonic() < deadline:
        if display_answers(number, timeout=2):
            return proc
        time.sleep(0.02)
    _stop(proc)  # exited (the number is taken) or never answered
    return None


@contextmanager
def virtual_display(*, rng: random.Random | None = None):
    """Yield an X display for ParaView: ``$DISPLAY``, else a private Xvfb server for the block.

    Parameters
    ----------
    rng : random.Random, optional
        Draws the display numbers (a fresh, unseeded one by default: the number never
        changes a result).

    Yields
    ------
    str
        ``":N"``.

    Raises
    ------
    DVRInputError
        Xvfb is not installed, or no server started that answered (its messages included).
    """
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise DVRInputError("no DISPLAY and Xvfb is not installed (apt-get install xvfb)")
    rng = rng or random.Random()
    with tempfile.TemporaryFile() as errors:
        tried = []
        for _ in range(START_ATTEMPTS):
            number = rng.randrange(*DISPLAY_RANGE)
            tried.append(number)
            proc = _start(xvfb, number, errors)
            if proc is not None:
                break
            log.info("Xvfb could not serve display :%d; trying another number", number)
        else:
            errors.seek(0)
            said = errors.read().decode(errors="replace").strip().splitlines()[-3:]
            raise DVRInputError(
                f"Xvfb started on none of the displays {', '.join(f':{n}' for n in tried)}"
                f" (its last words: {' / '.join(said) or 'none'})"
            )
        try:
            yield f":{number}"
        finally:
            _stop(proc)
