"""The live view's front door: at most ``max_viewers`` viewers, and each one's backlog bounded in bytes.

foxglove-sdk 0.30 has neither: its server takes every client, and bounds each one's queue in messages only
(``message_backlog_size``), so a slow viewer of big JPEGs holds "backlog x largest image" bytes. The gate is a small
TCP proxy in front of it. Viewers connect to the gate (the address the user asked for); the SDK server listens on a
loopback port of its own, and the gate connects each viewer to it:

* **Viewer cap.** A viewer beyond ``max_viewers`` gets ``HTTP 503`` with a one-line reason before any WebSocket
  handshake (Foxglove shows the connection as failed) and is logged; the ones connected are untouched.
* **Backlog in bytes.** The gate reads the server's WebSocket frames as they come (so the SDK's own queue stays
  short) and queues them for the viewer's socket. A ``messageData`` frame (binary opcode 1: one message of one
  channel, a whole WebSocket frame) that would take the viewer's queue beyond ``backlog_bytes`` is dropped instead;
  control and text frames (advertisements, server info) are never dropped. Dropping whole frames keeps the stream
  valid: the gate removes ``Sec-WebSocket-Extensions`` from the viewer's handshake, so frames are never compressed
  with a shared context. The kernel's socket send buffer (a few MB on loopback) comes on top, as for any socket.

It runs an asyncio loop on one daemon thread; nothing here touches Zenoh or the SDK.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from dataclasses import dataclass

log = logging.getLogger("drivebench.viz")

HANDSHAKE_LIMIT_BYTES = 16 * 1024  # a viewer's HTTP upgrade request is well under 1 kB
HANDSHAKE_TIMEOUT_S = 10.0  # a connection that never completes its request holds no viewer slot for long
_BINARY, _MESSAGE_DATA = 0x2, 0x01


@dataclass
class GateStats:
    """Counters of the gate (read from any thread; written by the gate's loop only)."""

    viewers: int = 0  # connected now
    served: int = 0  # viewers let in so far
    refused: int = 0  # viewers turned away: the cap was reached
    dropped_messages: int = 0  # messageData frames dropped: a viewer's backlog was full
    dropped_bytes: int = 0
    peak_backlog_bytes: int = 0  # the most bytes ever queued for one viewer


class ViewerGate:
    """A TCP proxy from ``host:port`` (port 0: any free port, see :attr:`port`) to the Foxglove server at
    ``upstream_port`` on loopback, enforcing ``max_viewers`` and ``backlog_bytes`` (see the module docstring)."""

    def __init__(self, *, host: str, port: int, upstream_port: int, max_viewers: int, backlog_bytes: int):
        if max_viewers < 1:
            raise ValueError(f"max_viewers must be >= 1, got {max_viewers}")
        if backlog_bytes < 1:
            raise ValueError(f"backlog_bytes must be >= 1, got {backlog_bytes}")
        self.max_viewers = max_viewers
        self.backlog_bytes = backlog_bytes
        self.stats = GateStats()
        self._upstream_port = upstream_port
        self._loop = asyncio.new_event_loop()
        self._connections: set[asyncio.Task] = set()
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(
                    self._on_viewer, host=host or None, port=port, reuse_address=True, limit=HANDSHAKE_LIMIT_BYTES
                )
            )
        except OSError:
            self._loop.close()
            raise
        self.port = self._server.sockets[0].getsockname()[1]
        self._thread = threading.Thread(target=self._loop.run_forever, name="viz-gate", daemon=True)
        self._thread.start()

    # -- one viewer --

    async def _on_viewer(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None  # a connection callback runs as a task of its own
        self._connections.add(task)
        try:
            try:
                request = await asyncio.wait_for(_read_head(reader), HANDSHAKE_TIMEOUT_S)
            except TimeoutError:
                return
            if request is None:
                return
            if self.stats.viewers >= self.max_viewers:
                self.stats.refused += 1
                log.warning(
                    "refused a viewer from %s: %d viewers already connected (max_viewers %d)",
                    _peer(writer),
                    self.stats.viewers,
                    self.max_viewers,
                )
                body = f"drivebench view: {self.stats.viewers} viewers already connected (max_viewers)\n".encode()
                writer.write(
                    b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                    b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body
                )
                await writer.drain()
                return
            self.stats.viewers += 1
            self.stats.served += 1
            try:
                await self._proxy(request, reader, writer)
            finally:
                self.stats.viewers -= 1
        except (ConnectionError, asyncio.IncompleteReadError, OSError):
            pass  # a viewer that went away
        finally:
            writer.close()
            self._connections.discard(asyncio.current_task())

    async def _proxy(self, request: bytes, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self._upstream_port)
        try:
            up_writer.write(_without_extensions(request))
            await up_writer.drain()
            upstream = asyncio.ensure_future(_quietly(self._server_to_viewer(up_reader, writer)))
            downstream = asyncio.ensure_future(_quietly(_copy(reader, up_writer)))
            # Either side closing ends both: a viewer that left, or the server stopping.
            _, pending = await asyncio.wait({upstream, downstream}, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        finally:
            up_writer.close()

    async def _server_to_viewer(self, up_reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """The server's handshake reply as it is, then its frames, dropping messageData beyond the byte budget."""
        reply = await _read_head(up_reader)
        if reply is None:
            return
        writer.write(reply)
        if not reply.startswith(b"HTTP/1.1 101"):  # no WebSocket (an error page): pass the rest through
            await _copy(up_reader, writer)
            return
        transport = writer.transport
        while True:
            frame = await _read_frame(up_reader)
            queued = transport.get_write_buffer_size()
            # Only a whole (FIN) binary frame holding messageData; never a fragment, text or control frame.
            droppable = frame[0] == (0x80 | _BINARY) and _payload_first_byte(frame) == _MESSAGE_DATA
            if droppable and queued + len(frame) > self.backlog_bytes:
                self.stats.dropped_messages += 1
                self.stats.dropped_bytes += len(frame)
                continue
            writer.write(frame)
            self.stats.peak_backlog_bytes = max(self.stats.peak_backlog_bytes, transport.get_write_buffer_size())
            if transport.is_closing():
                return

    # -- shutdown --

    def close(self) -> None:
        """Stop listening and disconnect every viewer."""

        async def stop() -> None:
            self._server.close()
            for task in list(self._connections):
                task.cancel()
            await asyncio.gather(*self._connections, return_exceptions=True)

        if self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(stop(), self._loop).result(timeout=5)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=5)
        self._loop.close()


async def _read_head(reader: asyncio.StreamReader) -> bytes | None:
    """An HTTP request or response head, up to and with its blank line; None when the peer closed or sent junk."""
    try:
        return await reader.readuntil(b"\r\n\r\n")
    except (asyncio.IncompleteReadError, asyncio.LimitOverrunError):
        return None


def _without_extensions(request: bytes) -> bytes:
    """The handshake without ``Sec-WebSocket-Extensions``: no permessage-deflate, so frames can be dropped whole."""
    lines = request.split(b"\r\n")
    return b"\r\n".join(line for line in lines if not line.lower().startswith(b"sec-websocket-extensions:"))


async def _read_frame(reader: asyncio.StreamReader) -> bytes:
    """One whole WebSocket frame (header and payload) as it came."""
    head = await reader.readexactly(2)
    length = head[1] & 0x7F
    extended = b""
    if length == 126:
        extended = await reader.readexactly(2)
    elif length == 127:
        extended = await reader.readexactly(8)
    if extended:
        length = int.from_bytes(extended, "big")
    mask = await reader.readexactly(4) if head[1] & 0x80 else b""
    return head + extended + mask + await reader.readexactly(length)


def _payload_first_byte(frame: bytes) -> int | None:
    length = frame[1] & 0x7F
    start = 2 + (2 if length == 126 else 8 if length == 127 else 0) + (4 if frame[1] & 0x80 else 0)
    return frame[start] if len(frame) > start and not frame[1] & 0x80 else None


async def _quietly(work) -> None:
    try:
        await work
    except (ConnectionError, asyncio.IncompleteReadError, OSError):
        pass  # the other end went away: the connection ends


async def _copy(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    while data := await reader.read(1 << 16):
        writer.write(data)
        await writer.drain()


def _peer(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    return f"{peer[0]}:{peer[1]}" if peer else "?"
