"""Writes a file outside its scratch (``path``: somewhere the test looks from outside)."""

from __future__ import annotations

from pathlib import Path

from support.hostile.base import Driving


class WriterBrain(Driving):
    def __init__(self, *, path: str):
        Path("inside-scratch.txt").write_text("allowed\n")  # its working directory is its scratch
        Path(path).write_text("written by a sandboxed brain\n")
