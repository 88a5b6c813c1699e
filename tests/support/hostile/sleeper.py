"""Sleeps in ``__init__`` (an hour)."""

from __future__ import annotations

import time

from support.hostile.base import Driving


class SleeperBrain(Driving):
    def __init__(self):
        time.sleep(3600)
