"""Forks hundreds of processes that stay alive."""

from __future__ import annotations

import os
import time

from support.hostile.base import Driving


class ForkerBrain(Driving):
    def __init__(self, *, processes: int = 500):
        for _ in range(int(processes)):
            if os.fork() == 0:
                time.sleep(600)
                os._exit(0)
