"""A Foxglove WebSocket viewer for the live-view tests: one that reads every message, and one that never reads."""

from __future__ import annotations

import json
import socket
import struct
import threading
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field

from websockets.client import ClientProtocol
from websockets.frames import Opcode
from websockets.sync.client import connect
from websockets.uri import parse_uri

SUBPROTOCOL = "foxglove.sdk.v1"


MESSAGE_DATA = 1


@dataclass
class Received:
    arrival: float  # time.monotonic()
    log_time_ns: int
    payload: bytes


@dataclass
class FoxgloveClient:
    """Reads everything on a background thread; subscribes to every advertised channel ``wanted`` accepts."""

    ws: object
    wanted: object  # topic -> bool
    server_info: dict = field(default_factory=dict)
    channels: dict[str, dict] = field(default_factory=dict)  # topic -> advertised channel
    messages: dict[str, list[Received]] = field(default_factory=lambda: defaultdict(list))  # topic -> messages
    _topic_of_subscription: dict[int, str] = field(default_factory=dict)
    _advertised: threading.Condition = field(default_factory=threading.Condition)

    def run(self) -> None:
        try:
            for message in self.ws:
                if isinstance(message, str):
                    self._on_text(json.loads(message))
                elif message[0] == MESSAGE_DATA:
                    subscription, log_time = struct.unpack_from("<IQ", message, 1)
                    self.messages[self._topic_of_subscription[subscription]].append(
                        Received(time.monotonic(), log_time, message[13:])
                    )
        except Exception:  # the connection closed under us at the end of a test
            pass

    def _on_text(self, message: dict) -> None:
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            subscriptions = []
            for channel in message["channels"]:
                if self.wanted(channel["topic"]):
                    subscription = len(self._topic_of_subscription)
                    self._topic_of_subscription[subscription] = channel["topic"]
                    subscriptions.append({"id": subscription, "channelId": channel["id"]})
            if subscriptions:
                self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            with self._advertised:
                self.channels.update({channel["topic"]: channel for channel in message["channels"]})
                self._advertised.notify_all()

    def wait_for_channels(self, topics: set[str], timeout_s: float = 10.0) -> None:
        with self._advertised:
            assert self._advertised.wait_for(lambda: topics <= set(self.channels), timeout=timeout_s), (
                f"never advertised: {topics - set(self.channels)}"
            )


@contextmanager
def foxglove_client(port: int, wanted=lambda topic: True):
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None, open_timeout=10) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        client = FoxgloveClient(ws=ws, wanted=wanted)
        reader = threading.Thread(target=client.run, daemon=True)
        reader.start()
        yield client


class StuckClient:
    """A viewer that connects, subscribes to everything advertised, and then never reads again.

    Sans-I/O ``websockets`` over a plain socket (64 kB receive buffer): once it stops calling ``recv`` nothing is
    read at all, so the kernel's socket buffers (a few MB on loopback), then the server's per-client backlog fill.
    """

    def __init__(self, port: int, topics: set[str]):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)  # before connecting: sets the window
        self.sock.connect(("127.0.0.1", port))
        self.protocol = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}"), subprotocols=[SUBPROTOCOL], max_size=None)
        self.protocol.send_request(self.protocol.connect())
        self._send()
        channels: dict[int, str] = {}
        deadline = time.monotonic() + 10
        while not topics <= set(channels.values()):
            assert time.monotonic() < deadline, f"never advertised: {topics - set(channels.values())}"
            self.sock.settimeout(max(0.1, deadline - time.monotonic()))
            self.protocol.receive_data(self.sock.recv(65536))
            for event in self.protocol.events_received():
                if getattr(event, "opcode", None) == Opcode.TEXT and json.loads(event.data)["op"] == "advertise":
                    channels.update({c["id"]: c["topic"] for c in json.loads(event.data)["channels"]})
            self._send()
        self.protocol.send_text(
            json.dumps(
                {
                    "op": "subscribe",
                    "subscriptions": [{"id": i, "channelId": channel} for i, channel in enumerate(channels)],
                }
            ).encode()
        )
        self._send()

    def _send(self) -> None:
        for data in self.protocol.data_to_send():
            self.sock.sendall(data)

    def drain(self, *, quiet_s: float = 1.0, limit_s: float = 10.0) -> tuple[int, bool]:
        """Read what is waiting, until ``quiet_s`` without data: (messageData frames read, closed by the server)."""
        self.sock.settimeout(quiet_s)
        frames, closed, deadline = 0, False, time.monotonic() + limit_s
        self.bytes_read = 0
        try:
            while time.monotonic() < deadline:
                data = self.sock.recv(1 << 20)
                if not data:
                    closed = True
                    break
                self.bytes_read += len(data)
                self.protocol.receive_data(data)
                frames += sum(
                    1
                    for event in self.protocol.events_received()
                    if getattr(event, "opcode", None) == Opcode.BINARY and event.data[0] == MESSAGE_DATA
                )
        except TimeoutError:
            pass
        except OSError:
            closed = True
        return frames, closed

    def close(self) -> None:
        self.sock.close()
