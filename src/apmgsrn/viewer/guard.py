"""What the viewer accepts from the network: who may talk to it, how much, and what a page may change.

The page talks to the server over one websocket (trame on wslink on aiohttp). Left as they come, those
layers trust every client that knows the default secret ``wslink-secret``: once it has said hello, wslink
reassembles a message into a buffer of the size its first chunk's header declares (up to 4 GiB, allocated
at once: 13 bytes cost a gigabyte); any client may call ``application.exit``; and any client may write any
key of the state every page shares (the list of files, the page's own template) before the server sees it.
:class:`ConnectionGuard` closes each of these where it enters, when the server binds:

- a random secret per run, handed only to the page the server serves (``POST /paraview/``, the trame
  client's own way of asking for its session), so a client that did not load the page cannot call the app;
- requests whose ``Host`` is not a loopback name are refused while the server listens on loopback (a
  foreign web page that rebinds its DNS name to 127.0.0.1 cannot read the page or the secret), and so is
  a websocket opened from a page of another origin;
- messages are reassembled by :class:`BoundedUnChunker`: memory grows with the bytes that arrive, never
  with what a header declares, and a message larger than the cap (the upload limit and a margin) closes
  the connection;
- only the RPCs the page uses are served, and a page's state changes are passed through the page's rules
  (:meth:`apmgsrn.viewer.page_state.PageState.accepts`) before any other page or the server sees them.
"""

from __future__ import annotations

import ipaddress
import logging
import secrets
import struct
from dataclasses import dataclass
from typing import Callable
from urllib.parse import urlsplit

import msgpack  # wslink's message format (the [viewer] extra)

from apmgsrn.errors import ApmgsrnError

logger = logging.getLogger(__name__)

# wslink's chunk header: message id, offset of this chunk, size of the whole message (uint32, little endian).
CHUNK_HEADER = struct.Struct("<III")
SESSION_PATH = "/paraview/"  # where the trame client asks for its session (sessionManagerURL's default)

# The RPCs the page uses; trame.state.update and trame.lifecycle.update are filtered further.
PAGE_RPCS = frozenset(
    {"trame.state.get", "trame.state.update", "trame.trigger", "trame.lifecycle.update", "trame.error.client",
     "trame.force.push"}
)

StateRule = Callable[[str, object], bool]


class MessageRefused(Exception):
    """A client sent a message the viewer does not take (too large, malformed): its connection is closed."""


def new_secret() -> str:
    """A random secret for one run of the viewer (256 bits, URL-safe text)."""
    return secrets.token_urlsafe(32)


@dataclass(frozen=True)
class GuardConfig:
    """Limits on what a client may send.

    Attributes:
        message_bytes: largest message (all its chunks together) once the client knows the secret.
        hello_bytes: largest message before that (the hello is about 100 bytes).
        pending_messages: messages a client may have partly sent at once.
        loopback_only: refuse requests whose ``Host`` is not a loopback name (set when listening on loopback).
    """

    message_bytes: int
    hello_bytes: int = 512
    pending_messages: int = 4
    loopback_only: bool = True


class BoundedUnChunker:
    """wslink's reassembly of chunked messages, with limits (a drop-in for ``wslink.chunking.UnChunker``).

    Chunks of a message must come in order (the wslink clients send them so); each is appended as it
    arrives, so memory follows the bytes received. Raises :class:`MessageRefused` for a declared size over
    the current limit, too many messages in flight, chunks out of order or past the declared size, or a
    payload that is not msgpack.
    """

    def __init__(self, config: GuardConfig) -> None:
        self.config = config
        self.max_message_size = config.hello_bytes
        self._pending: dict[int, tuple[int, bytearray]] = {}

    def set_max_message_size(self, size: int) -> None:
        """wslink raises the limit once the client has shown the secret (to 4 GiB): never past our cap."""
        self.max_message_size = min(int(size), self.config.message_bytes)

    def release_pending_messages(self) -> None:
        self._pending = {}

    def process_chunk(self, chunk: bytes) -> object | None:
        """Take one websocket frame; return the decoded message once its last chunk is in, else None."""
        if len(chunk) < CHUNK_HEADER.size:
            raise MessageRefused("a chunk shorter than its header")
        identifier, offset, total = CHUNK_HEADER.unpack_from(chunk)
        content = memoryview(chunk)[CHUNK_HEADER.size :]
        if total > self.max_message_size:
            raise MessageRefused(f"a message of {total:,} bytes (the limit is {self.max_message_size:,})")
        size, buffer = self._pending.get(identifier, (total, None))
        if buffer is None:
            if len(self._pending) >= self.config.pending_messages:
                raise MessageRefused("too many messages in flight")
            buffer = bytearray()
            self._pending[identifier] = (total, buffer)
        if size != total or offset != len(buffer) or offset + len(content) > total:
            raise MessageRefused("a chunk out of order or past its message's size")
        buffer += content
        if len(buffer) < total:
            return None
        del self._pending[identifier]
        try:
            return msgpack.unpackb(bytes(buffer))
        except Exception as exc:  # noqa: BLE001 - msgpack raises several types for hostile bytes
            raise MessageRefused(f"not a msgpack message ({type(exc).__name__})") from None


class ConnectionGuard:
    """Installs the viewer's limits on a trame/wslink server when it binds (see the module notes)."""

    def __init__(self, secret: str, config: GuardConfig, accepts: StateRule) -> None:
        """Args:
        secret: this run's secret (the server's ``authKey``).
        config: message limits and the ``Host`` check.
        accepts: ``accepts(key, value)``: may a page set state ``key`` to ``value``.
        """
        self.secret = secret
        self.config = config
        self.accepts = accepts
        self._socket_path = "/ws"  # the websocket's path, read from the application on install

    def install(self, ws_server) -> None:
        """trame's ``on_server_bind`` hook: guard the wslink endpoint and the HTTP routes of the application.

        Args:
            ws_server: wslink's aiohttp web server (its ``app`` not started yet).

        Raises:
            ApmgsrnError: a wslink/trame version whose internals differ from what this guard relies on
                (better not to serve than to serve unguarded).
        """
        from aiohttp import web
        from wslink.protocol import WslinkHandler

        app = ws_server.app
        endpoints = {  # aiohttp routes GET and HEAD of the websocket's path to the same handler
            (route.resource.canonical, route.handler.__self__)
            for route in app.router.routes()
            if isinstance(getattr(route.handler, "__self__", None), WslinkHandler)
        }
        if len(endpoints) != 1:
            raise ApmgsrnError(f"the viewer expects one wslink endpoint, found {len(endpoints)}; {_VERSIONS}")
        path, handler = endpoints.pop()
        for name in ("functionMap", "unchunkers", "connections", "onConnect", "onMessage"):
            if not hasattr(handler, name):
                raise ApmgsrnError(f"wslink's handler has no {name!r}; {_VERSIONS}")
        if not PAGE_RPCS <= set(handler.functionMap):
            raise ApmgsrnError(f"trame's RPCs changed ({sorted(PAGE_RPCS - set(handler.functionMap))}); {_VERSIONS}")
        self._guard_handler(handler)

        @web.middleware
        async def check_request(request, handler):
            return await self._check_request(request, handler)

        app.middlewares.append(check_request)
        app.router.add_post(SESSION_PATH, self._session)
        self._socket_path = path

    # ------------------------------------------------------------------------------------------ HTTP
    async def _check_request(self, request, handler):
        from aiohttp import web

        if self.config.loopback_only and not is_loopback_name(_host_name(request.host)):
            return web.Response(status=403, text="this viewer answers on 127.0.0.1 or localhost only\n")
        origin = request.headers.get("Origin")
        if request.headers.get("Upgrade", "").lower() == "websocket" and origin is not None:
            if _origin_authority(origin) != request.host.lower():
                return web.Response(status=403, text="websocket from a page of another origin refused\n")
        return await handler(request)

    async def _session(self, request):
        """The page's session: where its websocket is and the secret to say hello with."""
        from aiohttp import web

        # USE_HOST: the trame client puts the page's own host:port there (and wss: under https).
        body = {"sessionURL": f"ws://USE_HOST{self._socket_path}", "secret": self.secret}
        return web.json_response(body, headers={"Cache-Control": "no-store"})

    # ------------------------------------------------------------------------------------------ websocket
    def _guard_handler(self, handler) -> None:
        from aiohttp import WSCloseCode

        original_connect, original_message = handler.onConnect, handler.onMessage

        async def on_connect(request, client_id):
            await original_connect(request, client_id)
            handler.unchunkers[client_id] = BoundedUnChunker(self.config)

        async def on_message(is_binary, message, client_id):
            try:
                await original_message(is_binary, message, client_id)
            except MessageRefused as exc:
                await _close(handler, client_id, WSCloseCode.MESSAGE_TOO_BIG, str(exc))
            except Exception as exc:  # noqa: BLE001 - RPC errors are answered inside; this is a malformed message
                await _close(handler, client_id, WSCloseCode.PROTOCOL_ERROR, f"malformed ({type(exc).__name__})")

        handler.onConnect, handler.onMessage = on_connect, on_message
        functions = {uri: entry for uri, entry in handler.functionMap.items() if uri in PAGE_RPCS}
        functions["trame.state.update"] = self._filtered_update(*functions["trame.state.update"])
        functions["trame.lifecycle.update"] = _client_lifecycle(*functions["trame.lifecycle.update"])
        handler.functionMap = functions

    def _filtered_update(self, protocol, update):
        """``trame.state.update`` passing on only the changes the page's rules accept."""

        def filtered(protocol, changes=None, *_):
            accepted, refused = [], set()
            for change in changes if isinstance(changes, list) else []:
                key = change.get("key") if isinstance(change, dict) else None
                if not isinstance(key, str):
                    continue
                if self.accepts(key, change.get("value")):
                    accepted.append(change)
                else:
                    refused.add(key)
            if refused:
                logger.warning("refused a page's change of %s", ", ".join(sorted(refused)[:8]))
            if accepted:
                update(protocol, accepted)
            known = [key for key in refused if protocol.server.state.has(key)]
            if known:
                protocol.force_push_state(*known)  # the sending page goes back to the server's value

        return protocol, filtered


def _client_lifecycle(protocol, update):
    """``trame.lifecycle.update`` for the client's own events only (``client_connected`` etc.)."""

    def filtered(protocol, name=None, *_):
        if isinstance(name, str) and name.startswith("client_"):
            return update(protocol, name)
        return None

    return protocol, filtered


async def _close(handler, client_id: str, code: int, reason: str) -> None:
    logger.warning("closed a connection: %s", reason)
    socket = handler.connections.get(client_id)
    if socket is not None and not socket.closed:
        await socket.close(code=code, message=reason.encode("utf-8")[:120])


def _host_name(authority: str) -> str | None:
    """``host`` of a ``host:port`` (brackets of an IPv6 address removed); None if it does not parse."""
    try:
        return urlsplit(f"//{authority}").hostname
    except ValueError:
        return None


def _origin_authority(origin: str) -> str | None:
    """``host:port`` of an ``Origin`` header, lower case; None if it does not parse."""
    try:
        return urlsplit(origin).netloc.lower() or None
    except ValueError:
        return None


def is_loopback_name(host: str | None) -> bool:
    """Whether a host name or address is this machine's loopback (``localhost``, 127.0.0.0/8, ``::1``)."""
    if not host:
        return False
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


_VERSIONS = "install the versions the viewer is tested with: pip install 'apmgsrn[viewer]'"
