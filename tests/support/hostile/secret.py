"""Reads a secret file by its absolute path (a challenge's hidden folder) and prints it."""

from __future__ import annotations

from pathlib import Path

from support.hostile.base import Driving


class SecretBrain(Driving):
    def __init__(self, *, path: str):
        print("secret:", Path(path).read_text(), flush=True)
