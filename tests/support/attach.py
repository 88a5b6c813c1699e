"""A driver attached to a running stack: ``drivebench run --attach`` on the stack's router, as an operator starts
one against long-lived services. The fault tests (tests/test_faults.py) and the fault benchmark (benchmarks/faults.py)
start it this way."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from support.env import clean_env

CAMERA = "64x48"  # what the episode shows does not matter to a fault; a small frame keeps the stack light


def attach_driver(
    *, endpoint: str, run_id: str, out: Path, args: Sequence[str] = (), output: int = subprocess.PIPE
) -> subprocess.Popen:
    """Start ``drivebench run --attach`` for run ``run_id`` on the router at ``endpoint``, its results into ``out``.

    args: more of its command line (``("--max-sim-seconds", "600", "--realtime")``). output: where its stdout and
    stderr go (PIPE: text for ``communicate()``; DEVNULL). It runs in a session of its own, so that
    ``os.killpg(driver.pid, ...)`` kills the driver and nothing else of the stack."""
    argv = [sys.executable, "-m", "orchestrator.cli", "run", "--attach", "--router", endpoint, "--run-id", run_id]
    argv += ["--camera", CAMERA, "--out", str(out), *args]
    return subprocess.Popen(argv, stdout=output, stderr=output, text=True, env=clean_env(), start_new_session=True)
