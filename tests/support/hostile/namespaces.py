"""Tries to make a user namespace, the usual first step of a kernel exploit (root with every capability over the
namespaces it then makes), on frame 5: by the system call (``unshare(CLONE_NEWUSER)``) and by util-linux's
``unshare -U -r``. Prints what each did, and drives on."""

from __future__ import annotations

import ctypes
import subprocess
import sys

from brains.base import Action, Observation
from support.hostile.base import Driving

CLONE_NEWUSER = 0x10000000


class NamespaceBrain(Driving):
    def act(self, observation: Observation) -> Action:
        if observation.seq == 5:
            libc = ctypes.CDLL(None, use_errno=True)
            made = libc.unshare(CLONE_NEWUSER) == 0
            print(
                f"unshare(CLONE_NEWUSER): {'made' if made else f'refused, errno {ctypes.get_errno()}'}", file=sys.stderr
            )
            tool = subprocess.run(["unshare", "-U", "-r", "id", "-u"], capture_output=True, text=True)
            inside = tool.stdout.strip() if tool.returncode == 0 else f"refused: {tool.stderr.strip()}"
            print(f"unshare -U -r: {inside}", file=sys.stderr, flush=True)
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)
