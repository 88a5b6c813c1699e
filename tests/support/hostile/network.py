"""Opens a TCP connection to ``port`` on 127.0.0.1 (the test's listener, outside the sandbox)."""

from __future__ import annotations

import socket

from support.hostile.base import Driving


class NetworkBrain(Driving):
    def __init__(self, *, port: int):
        socket.create_connection(("127.0.0.1", int(port)), timeout=2.0).sendall(b"leaked\n")
