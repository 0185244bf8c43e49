"""Who may talk to the web app's server, and how much: token, origin, message sizes.

trame serves the page and its websocket with wslink on aiohttp.  :func:`install` hooks into
that server before it starts (trame's ``on_server_bind``):

* an aiohttp middleware asks every HTTP request -- the page, its scripts and the websocket
  handshake -- for the per-run secret token, given once in the address the app prints
  (``?secret=...``, as Jupyter does) and then kept in an HTTP-only, same-site cookie.  A
  websocket handshake must also come from the app's own origin (its ``Origin`` header names
  the address the page was loaded from) and name an allowed host (no DNS rebinding);
* wslink's own hello secret is set to the same token, so its default shared secret
  (``wslink-secret``) does not authenticate anyone;
* wslink's re-assembly of chunked messages is replaced by :class:`BoundedUnChunker`, which
  refuses (and closes the connection of) a chunk whose header claims more than the message
  limit, before anything is allocated, and stores only the bytes actually received.  The size
  of a single websocket frame is bounded by aiohttp (``max_msg_size``, from trame's
  ``ws_max_msg_size``) before its payload is read;
* a whole message must be a well-formed wslink call (a map with a text ``id``, a text
  ``method``, a list ``args`` and a map ``kwargs`` that fit the method's parameters); any other
  is refused quietly (:func:`message_problem`): one log line and an error reply, the client
  stays connected.  wslink's ``application.exit`` calls (no page makes them) are refused the
  same way, and a call that fails in the server is one log line, never a traceback (nor a
  trace sent to the client).  What the page's calls carry is checked by
  :mod:`dvr_perception.app.page_input`.
"""

from __future__ import annotations

import asyncio
import functools
import hmac
import inspect
import logging
import secrets
import struct
import time
from urllib.parse import urlsplit

import msgpack

__all__ = [
    "AUTH_MESSAGE_BYTES",
    "FRAME_BYTES",
    "BoundedUnChunker",
    "ConnectionGuard",
    "message_problem",
    "new_token",
    "quiet_disconnects",
]

log = logging.getLogger("dvr_perception.app")

#: Largest websocket frame (one chunk of a wslink message) the server reads.
FRAME_BYTES = 4 * 2**20
#: Largest message a client may send before it has authenticated (wslink's own default).
AUTH_MESSAGE_BYTES = 512
#: Most chunked messages a connection may have under way at once.
MAX_PENDING = 4
#: wslink chunk header: message id, offset and total size (three little-endian uint32).
_HEADER = struct.Struct("<III")
#: Hosts the loopback server answers to (anything else is a DNS-rebinding attempt).
#: wslink's (JSON-RPC's) error code of a malformed call.
INVALID_REQUEST = -32600
#: wslink calls no page makes that would stop the server for every user.
REFUSED_METHODS = frozenset({"application.exit", "application.exit.later"})
#: Longest text of a page's script error written to the log.
CLIENT_ERROR_CHARS = 300
_LOOPBACK = frozenset({"127.0.0.1", "localhost", "::1"})
_ANY_HOST = frozenset({"", "0.0.0.0", "::"})


def new_token() -> str:
    """Return a fresh random secret (43 URL-safe characters, 256 bits)."""
    return secrets.token_urlsafe(32)


class BoundedUnChunker:
    """Re-assemble wslink's chunked messages within a size limit.

    Same interface as ``wslink.chunking.UnChunker``; wslink raises the limit once a client has
    sent the right secret (``set_max_message_size``), which here only goes up to ``limit``.

    Parameters
    ----------
    limit : int
        Largest whole message, in bytes, of an authenticated client.
    refuse : callable
        Called with a one-line reason when a chunk breaks a limit (closes the connection).
    """

    def __init__(self, limit: int, refuse) -> None:
        self.limit = int(limit)
        self.max_message_size = min(AUTH_MESSAGE_BYTES, self.limit)
        self._refuse = refuse
        self._pending: dict[int, tuple[int, bytearray]] = {}
        self.refused = False

    def set_max_message_size(self, size) -> None:
        """Raise (or lower) the message limit, never above ``limit``."""
        self.max_message_size = min(int(size), self.limit)

    def release_pending_messages(self) -> None:
        """Forget the messages under way."""
        self._pending = {}

    def _fail(self, reason: str) -> None:
        self._pending = {}
        self.refused = True
        self._refuse(reason)

    def process_chunk(self, chunk: bytes):
        """Add one chunk; return the decoded message once it is complete (else ``None``)."""
        if self.refused:
            return None
        if len(chunk) < _HEADER.size:
            self._fail(f"a {len(chunk)}-byte frame is shorter than a chunk header")
            return None
        msg_id, offset, total = _HEADER.unpack_from(chunk)
        content = memoryview(chunk)[_HEADER.size :]
        entry = self._pending.get(msg_id)
        if entry is None:
            under_way = sum(t for t, _ in self._pending.values())
            if total == 0 or total + under_way > self.max_message_size:
                self._fail(
                    f"a message claiming {total} bytes (limit {self.max_message_size} bytes)"
                )
                return None
            if len(self._pending) >= MAX_PENDING:
                self._fail(f"more than {MAX_PENDING} chunked messages under way")
                return None
            entry = (total, bytearray())
            self._pending[msg_id] = entry
        expected, buf = entry
        if total != expected or offset != len(buf) or len(buf) + len(content) > total:
            self._fail(f"a chunk that does not continue its message {msg_id}")
            return None
        buf += content
        if len(buf) < total:
            return None
        del self._pending[msg_id]
        try:
            return msgpack.unpackb(bytes(buf))
        except (ValueError, msgpack.UnpackException) as exc:
            self._fail(f"a message that is not msgpack ({type(exc).__name__})")
            return None


class _Unchunkers(dict):
    """wslink's per-connection un-chunkers, each one a :class:`BoundedUnChunker`."""

    def __init__(self, handler, limit: int) -> None:
        super().__init__()
        self._handler = handler
        self._limit = limit

    def __setitem__(self, client_id, _unchunker) -> None:
        def refuse(reason: str) -> None:
            log.warning("websocket client refused: %s; closing the connection", reason)
            ws = self._handler.connections.get(client_id)
            if ws is not None and not ws.closed:
                from aiohttp import WSCloseCode

                asyncio.get_running_loop().create_task(
                    ws.close(code=WSCloseCode.MESSAGE_TOO_BIG, message=b"message refused")
                )

        log.info("browser client %s connected", client_id)
        super().__setitem__(client_id, BoundedUnChunker(self._limit, refuse))

    def __delitem__(self, client_id) -> None:
        log.info("browser client %s disconnected", client_id)
        super().__delitem__(client_id)


def _tolerant(send):
    """Wrap a wslink send so that a client gone meanwhile costs one log line, no traceback.

    wslink logs an exception raised while it answers a client as three error lines (the
    second a whole traceback); a client that closed its connection is no error of the server.
    """

    async def send_or_note(*args, **kwargs):
        try:
            return await send(*args, **kwargs)
        except ConnectionError as exc:  # aiohttp's ClientConnectionResetError is one
            _note_disconnect(exc)
            return None

    return send_or_note


_last_note = [0.0]


def _note_disconnect(exc: BaseException) -> None:
    """Log a client that went away mid-message: one warning line (at most every 5 s)."""
    now = time.monotonic()
    level = logging.WARNING if now - _last_note[0] > 5.0 else logging.DEBUG
    _last_note[0] = now
    log.log(level, "a client disconnected abruptly (%s: %s)", type(exc).__name__, exc)


def message_problem(rpc, functions=None) -> str | None:
    """Say what makes ``rpc`` no well-formed wslink call (``None``: nothing).

    ``functions`` maps method names to ``(object, function)`` (wslink's ``functionMap``): the
    arguments must then fit the method's parameters.

    Examples
    --------
    >>> message_problem({"wslink": "1.0", "id": "rpc:c1:1", "args": []})
    'a message without a method'
    >>> message_problem({"id": "rpc:c1:2", "method": "m", "args": [1], "kwargs": {}}) is None
    True
    """
    if not isinstance(rpc, dict):
        return f"a message that is no map ({type(rpc).__name__})"
    rpc_id = rpc.get("id")
    if not isinstance(rpc_id, str) or not 0 < len(rpc_id) <= 200:
        return "a message without a text id"
    method = rpc.get("method")
    if not isinstance(method, str) or not 0 < len(method) <= 200:
        return "a message without a method"
    args, kwargs = rpc.get("args", []), rpc.get("kwargs", {})
    if not isinstance(args, list):
        return f"{method}: arguments that are no list"
    if not isinstance(kwargs, dict) or not all(isinstance(k, str) for k in kwargs):
        return f"{method}: keyword arguments that are no map of names"
    if method in REFUSED_METHODS:
        return f"{method}: not a call of the page"
    entry = (functions or {}).get(method)
    if entry is not None:
        try:
            inspect.signature(entry[1]).bind(entry[0], *args, **kwargs)
        except TypeError:
            return f"{method}: {len(args)} arguments that do not fit it"
    return None


def _checked_messages(handler):
    """Wrap wslink's ``handler.onCompleteMessage``: a malformed call is refused quietly."""
    complete = handler.onCompleteMessage

    async def on_complete(rpc, client_id):
        problem = message_problem(rpc, handler.functionMap)
        if problem is None:
            return await complete(rpc, client_id)
        log.warning("websocket client %s: message refused: %s", client_id, problem)
        rpc_id = rpc.get("id") if isinstance(rpc, dict) else None
        if isinstance(rpc_id, str) and 0 < len(rpc_id) <= 200:
            await handler.sendWrappedError(
                rpc_id, INVALID_REQUEST, f"message refused: {problem}", client_id=client_id
            )
        return None

    return on_complete


def _quiet_call(method: str, func):
    """Wrap one of wslink's call functions: an exception is one log line, the answer ``None``.

    wslink would log the exception as a traceback and send that trace to the client; a call
    whose arguments make the server fail is the client's fault (the page's own calls are
    checked by :mod:`dvr_perception.app.page_input`), so it costs one warning line (the
    traceback only at debug level).
    """

    def failed(exc: Exception) -> None:
        text = " ".join(str(exc).split())[:200]
        log.warning("websocket call %s refused: %s: %s", method, type(exc).__name__, text)
        log.debug("websocket call %s failed", method, exc_info=exc)

    if inspect.iscoroutinefunction(func):

        @functools.wraps(func)
        async def call_async(obj, *args, **kwargs):
            try:
                return await func(obj, *args, **kwargs)
            except Exception as exc:
                failed(exc)
                return None

        return call_async

    @functools.wraps(func)
    def call(obj, *args, **kwargs):
        try:
            return func(obj, *args, **kwargs)
        except Exception as exc:
            failed(exc)
            return None

    return call


def _one_line_client_error(func):
    """Wrap ``trame.error.client``: the page's script error is logged as one short line."""

    @functools.wraps(func)
    def client_error(obj, message):
        text = " ".join(str(message).split())
        text = "".join(c if c.isprintable() else "?" for c in text)[:CLIENT_ERROR_CHARS]
        return func(obj, text)

    return client_error


class ConnectionGuard:
    """The token, origin and message-size checks of one app server.

    Parameters
    ----------
    token : str
        The per-run secret.
    host : str
        Address the server listens on (``127.0.0.1`` by default).
    message_bytes : int
        Largest whole websocket message of an authenticated client.
    """

    def __init__(self, token: str, host: str, message_bytes: int) -> None:
        self.token = str(token)
        self.host = str(host)
        self.message_bytes = int(message_bytes)

    @staticmethod
    def cookie_name(host_header: str) -> str:
        """Name of the token cookie: one per port (cookies are shared by all ports of a host)."""
        try:
            port = urlsplit(f"//{host_header}").port or 80
        except ValueError:
            port = 0
        return f"dvr_perception_token_{port}"

    # -- checks --------------------------------------------------------------------------------
    def valid(self, text) -> bool:
        """Whether ``text`` is the token (constant-time comparison)."""
        return isinstance(text, str) and hmac.compare_digest(text.encode(), self.token.encode())

    def host_allowed(self, host_header: str) -> bool:
        """Whether a request's ``Host`` names this server (loopback or ``--host``)."""
        try:
            parts = urlsplit(f"//{host_header}")
            name = (parts.hostname or "").lower()
            _ = parts.port  # a port that is no number raises
        except ValueError:
            return False
        if self.host in _ANY_HOST:
            return bool(name)
        return name in _LOOPBACK or name == self.host.lower().strip("[]")

    def origin_allowed(self, origin, host_header: str, scheme: str) -> bool:
        """Whether a websocket's ``Origin`` is the app's own page (same scheme, host, port)."""
        if not origin or not host_header:
            return False
        return origin.lower() == f"{scheme}://{host_header}".lower()

    # -- aiohttp -------------------------------------------------------------------------------
    def middleware(self):
        """Return the aiohttp middleware that checks every request."""
        from aiohttp import web

        @web.middleware
        async def check(request, handler):
            websocket = request.headers.get("Upgrade", "").lower() == "websocket"
            given = request.query.get("secret")
            cookie = self.cookie_name(request.host)
            known = self.valid(given) or self.valid(request.cookies.get(cookie))
            where = f"{request.method} {request.path} from {request.remote}"
            if not self.host_allowed(request.host):
                log.warning("refused %s: host %r is not this server", where, request.host)
                raise web.HTTPForbidden(text="unknown host\n")
            if websocket:
                origin = request.headers.get("Origin")
                if not self.origin_allowed(origin, request.host, request.scheme):
                    log.warning("refused websocket %s: origin %r", where, origin)
                    raise web.HTTPForbidden(text="websocket from another origin\n")
            if not known:
                log.warning("refused %s: no valid token", where)
                raise web.HTTPForbidden(
                    text="open the address printed by 'dvr-perception app' (it ends in "
                    "?secret=...)\n"
                )
            if not websocket and request.path in ("/", "/index.html") and given is None:
                # a reload: the page needs the secret in its address for the websocket hello
                raise web.HTTPFound(f"/index.html?secret={self.token}")
            response = await handler(request)
            if given is not None:
                response.set_cookie(cookie, self.token, httponly=True, samesite="Strict", path="/")
            return response

        return check

    def install(self, wslink_server, protocol) -> None:
        """Install the checks in wslink's aiohttp server (call before it starts).

        ``protocol`` is trame's wslink server protocol, whose hello secret becomes the token.
        """
        app = wslink_server.app
        app.middlewares.append(self.middleware())
        handlers = getattr(wslink_server, "_ws_handlers", None)
        if not handlers:
            msg = "wslink server without websocket handlers: cannot bound message sizes"
            raise RuntimeError(msg)
        for handler in handlers:
            if not isinstance(getattr(handler, "unchunkers", None), dict):
                msg = "wslink handler without 'unchunkers': cannot bound message sizes"
                raise RuntimeError(msg)
            handler.unchunkers = _Unchunkers(handler, self.message_bytes)
            for name in ("sendWrappedMessage", "sendWrappedError"):
                setattr(handler, name, _tolerant(getattr(handler, name)))
            if not callable(getattr(handler, "onCompleteMessage", None)):
                msg = "wslink handler without 'onCompleteMessage': cannot check messages"
                raise RuntimeError(msg)
            handler.onCompleteMessage = _checked_messages(handler)
            calls = handler.functionMap
            if "trame.error.client" in calls:
                obj, func = calls["trame.error.client"]
                calls["trame.error.client"] = (obj, _one_line_client_error(func))
            for method, (obj, func) in list(calls.items()):
                calls[method] = (obj, _quiet_call(method, func))
        protocol.updateSecret(self.token)


#: Loggers of the web stack whose records a client going away may trigger.
_STACK_LOGGERS = (
    "asyncio",
    "aiohttp.server",
    "aiohttp.web",
    "aiohttp.websocket",
    "wslink.protocol",
    "wslink.backends.aiohttp",
    "trame_server.protocol",
)


class _OneLine(logging.Filter):
    """Turn a disconnect traceback, or wslink's two-line refusal, into one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, (ConnectionError, asyncio.CancelledError)) or (
            exc is not None and type(exc).__name__ == "ClientConnectionResetError"
        ):
            _note_disconnect(exc)
            return False
        if str(record.msg).startswith("wslink is not expecting text message"):
            text = record.getMessage().split("\n")[-1].lstrip("> ")
            log.warning("websocket client refused: %s", text)
            return False
        return True


def quiet_disconnects() -> None:
    """Log a client going away as one line, never as a traceback (idempotent)."""
    for name in _STACK_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, _OneLine) for f in logger.filters):
            logger.addFilter(_OneLine())
