"""One WebSocket port for both Foxglove subprotocols (standard library only; no rclpy, no SDK).

The Foxglove SDK's server (foxglove-sdk 0.30.3, and its newest source) accepts only the
subprotocol ``foxglove.sdk.v1`` and answers ``foxglove.websocket.v1``, which Lichtblick before
1.22, older Foxglove Studio builds and every client built on ``@foxglove/ws-protocol`` offer,
with HTTP 400. The two are the same protocol under two names (the ``foxglove.sdk.v1`` ops and
binary messages are those of ``foxglove.websocket.v1``).

:class:`SubprotocolGateway` listens on the public port and relays each connection byte for byte
to the SDK's server on a loopback port. Only the opening handshake is touched: a client that
offers ``foxglove.websocket.v1`` but not ``foxglove.sdk.v1`` has its request sent on offering
``foxglove.sdk.v1``, and the server's answer comes back naming ``foxglove.websocket.v1``
(``Sec-WebSocket-Accept`` depends on the key alone, so the handshake stays valid). Every other
request passes unchanged, so the SDK still refuses what it does not speak. Both kinds of client
thus get the very bytes of the one server: the same channels, messages and drop policy (the
relay reads from the server only as fast as the client takes, so a slow client's backlog is
the server's, which drops its oldest messages).
"""

from __future__ import annotations

import asyncio
import threading

SDK_SUBPROTOCOL = 'foxglove.sdk.v1'
LEGACY_SUBPROTOCOL = 'foxglove.websocket.v1'
#: Bytes an HTTP head may take at most (requests of browsers and Foxglove clients: < 2 kB).
HEAD_LIMIT = 16384
_PROTOCOL_HEADER = b'sec-websocket-protocol'
_END = b'\r\n\r\n'


def _header_lines(head: bytes) -> list[bytes]:
    return head[:-len(_END)].split(b'\r\n') if head.endswith(_END) else head.split(b'\r\n')


def _is_protocol_header(line: bytes) -> bool:
    name, colon, _ = line.partition(b':')
    return bool(colon) and name.strip().lower() == _PROTOCOL_HEADER


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocols an HTTP upgrade request offers (every Sec-WebSocket-Protocol header)."""
    offered = []
    for line in _header_lines(head)[1:]:
        if _is_protocol_header(line):
            value = line.partition(b':')[2].decode('latin-1')
            offered += [token.strip() for token in value.split(',') if token.strip()]
    return offered


def _with_protocol(head: bytes, subprotocol: str) -> bytes:
    """``head`` with its Sec-WebSocket-Protocol header(s) replaced by one naming ``subprotocol``."""
    lines = _header_lines(head)
    kept = [line for line in lines[1:] if not _is_protocol_header(line)]
    return b'\r\n'.join([lines[0], *kept, b'Sec-WebSocket-Protocol: ' + subprotocol.encode()]) + _END


def upstream_request(head: bytes) -> tuple[bytes, str | None]:
    """(the request head to send to the SDK, the subprotocol to name to the client instead of
    the SDK's, or None to pass its answer unchanged)."""
    offered = offered_subprotocols(head)
    if SDK_SUBPROTOCOL in offered or LEGACY_SUBPROTOCOL not in offered:
        return head, None
    return _with_protocol(head, SDK_SUBPROTOCOL), LEGACY_SUBPROTOCOL


def client_response(head: bytes, subprotocol: str | None) -> bytes:
    """The SDK's response head as the client must see it: a 101 naming ``subprotocol`` (None:
    unchanged; any other status passes unchanged)."""
    if subprotocol is None or not head.startswith(b'HTTP/1.1 101'):
        return head
    return _with_protocol(head, subprotocol)


class SubprotocolGateway:
    """Listens on ``host``:``port`` (0: any free port) and relays every connection to the
    WebSocket server on 127.0.0.1:``upstream_port``, rewriting the handshake of
    ``foxglove.websocket.v1`` clients (see the module). Runs its own asyncio loop in a daemon
    thread; ``close()`` ends it and every relayed connection. OSError when it cannot listen."""

    def __init__(self, host: str, port: int, upstream_port: int, chunk: int = 65536):
        self._upstream_port, self._chunk = upstream_port, chunk
        self._loop = asyncio.new_event_loop()
        self._relays: set[asyncio.Task] = set()
        #: Connections relayed so far, by the subprotocol the client was answered with.
        self.connections = {SDK_SUBPROTOCOL: 0, LEGACY_SUBPROTOCOL: 0}
        self._thread = threading.Thread(target=self._loop.run_forever, name='foxglove-gateway', daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(
                asyncio.start_server(self._relay, host, port, limit=HEAD_LIMIT), self._loop).result(10.0)
        except BaseException:
            self._stop_loop()
            raise

    @property
    def port(self) -> int:
        return self._server.sockets[0].getsockname()[1]

    async def _relay(self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self._relays.add(task)
        server_writer = None
        try:
            head = await client_reader.readuntil(_END)
            request, answer_as = upstream_request(head)
            server_reader, server_writer = await asyncio.open_connection('127.0.0.1', self._upstream_port,
                                                                         limit=HEAD_LIMIT)
            server_writer.write(request)
            await server_writer.drain()
            response = await server_reader.readuntil(_END)
            client_writer.write(client_response(response, answer_as))
            await client_writer.drain()
            if response.startswith(b'HTTP/1.1 101'):
                self.connections[answer_as or SDK_SUBPROTOCOL] += 1
            for ended in await asyncio.gather(self._pump(client_reader, server_writer),
                                              self._pump(server_reader, client_writer), return_exceptions=True):
                if isinstance(ended, BaseException) and not isinstance(ended, ConnectionError):
                    raise ended
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            pass  # a client that left, or a head too long / cut short: its connection is closed below
        finally:
            self._relays.discard(task)
            for writer in (client_writer, server_writer):
                if writer is not None:
                    writer.close()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Copy until end of file, reading no faster than ``writer`` drains (back pressure), then
        close ``writer`` (so the other direction ends too)."""
        try:
            while data := await reader.read(self._chunk):
                writer.write(data)
                await writer.drain()
        finally:
            writer.close()

    async def _shutdown(self) -> None:
        self._server.close()
        relays = list(self._relays)
        for task in relays:
            task.cancel()  # closes both ends (the relay's finally)
        await asyncio.gather(*relays, return_exceptions=True)
        await self._server.wait_closed()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5.0)
        if not self._thread.is_alive():
            self._loop.close()

    def close(self) -> None:
        """Stop listening and close every relayed connection."""
        if self._loop.is_closed():
            return
        try:
            asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop).result(5.0)
        finally:
            self._stop_loop()
