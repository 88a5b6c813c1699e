"""Prints a gigabyte."""

from __future__ import annotations

import sys

from support.hostile.base import Driving

LINE = "x" * ((1 << 20) - 1) + "\n"


class ShouterBrain(Driving):
    def __init__(self, *, megabytes: int = 1024):
        for _ in range(int(megabytes)):
            sys.stdout.write(LINE)
        sys.stdout.flush()
