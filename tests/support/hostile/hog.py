"""Allocates tens of GB, in chunks it touches."""

from __future__ import annotations

from support.hostile.base import Driving

CHUNK_BYTES = 64 << 20


class HogBrain(Driving):
    def __init__(self, *, gigabytes: int = 40):
        self._kept = [bytearray(CHUNK_BYTES) for _ in range(int(gigabytes) * (1 << 30) // CHUNK_BYTES)]
