"""A minimal Foxglove WebSocket client (the `websockets` library; subprotocol foxglove.sdk.v1 or
foxglove.websocket.v1) for the live view's bench, snapshot and tests: it subscribes to every
advertised channel and keeps what it receives. Protobuf channels are decoded with the schema
the server advertises (protobuf).
"""

from __future__ import annotations

import asyncio
import base64
import json
import socket
import struct
import threading
import time

from scenario_nodes.foxglove_gateway import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL  # noqa: F401 (re-exported)

SUBPROTOCOL = SDK_SUBPROTOCOL
MESSAGE_DATA = 1


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class FoxgloveClient(threading.Thread):
    """Connects to ws://127.0.0.1:``port`` offering ``subprotocol`` (retrying until the server is
    up or ``seconds`` pass), subscribes to every channel, keeps (log time, payload) per topic
    (``keep``; else only counts) and the bytes per topic until the server closes, ``stop()`` or
    ``seconds``."""

    def __init__(self, port: int, seconds: float = 600.0, keep: bool = True, subprotocol: str = SUBPROTOCOL):
        super().__init__(daemon=True)
        self.port, self.seconds, self.keep, self.offered = port, seconds, keep, subprotocol
        self.channels: dict[int, dict] = {}
        self.messages: dict[str, list] = {}
        self.bytes: dict[str, int] = {}
        self.received_at: dict[str, list] = {}  # topic -> [first, last] time.monotonic() of receipt
        self.count = 0
        self.subprotocol = None  # what the server answered
        self.subscribed_at = None  # time.monotonic() of the subscription
        self.error = None
        self._stopping = False

    def stop(self, timeout: float = 5.0) -> None:
        self._stopping = True
        self.join(timeout)

    def topic(self, name: str) -> dict | None:
        return next((c for c in self.channels.values() if c['topic'] == name), None)

    def run(self) -> None:
        try:
            asyncio.run(self._run())
        except Exception as error:  # noqa: BLE001 - kept for the caller to report
            self.error = error

    async def _run(self) -> None:
        import websockets
        deadline = time.monotonic() + self.seconds
        while True:
            try:
                ws = await websockets.connect(f'ws://127.0.0.1:{self.port}', subprotocols=[self.offered],
                                              max_size=None)
                break
            except OSError:
                if self._stopping or time.monotonic() > deadline:
                    return
                await asyncio.sleep(0.05)
        self.subprotocol = ws.subprotocol
        async with ws:
            while not self._stopping and time.monotonic() < deadline:
                try:
                    message = await asyncio.wait_for(ws.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return
                if isinstance(message, str):
                    op = json.loads(message)
                    if op['op'] == 'advertise':
                        self.channels.update({c['id']: c for c in op['channels']})
                        await ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
                            {'id': c['id'], 'channelId': c['id']} for c in op['channels']]}))
                        self.subscribed_at = time.monotonic()
                    continue
                if message[0] != MESSAGE_DATA:  # e.g. the server's time (opcode 2)
                    continue
                _, subscription, log_time = struct.unpack_from('<BIQ', message)
                self.count += 1
                topic = self.channels[subscription]['topic']
                self.bytes[topic] = self.bytes.get(topic, 0) + len(message)
                self.received_at.setdefault(topic, [time.monotonic(), 0.0])[1] = time.monotonic()
                if self.keep:
                    self.messages.setdefault(topic, []).append((log_time, message[13:]))


def protobuf_class(channel: dict):
    """The message class of a protobuf channel, built from the FileDescriptorSet it advertises."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel['schema']))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel['schemaName']))
