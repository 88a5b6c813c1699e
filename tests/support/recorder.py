"""The recorder as real processes: its CLI, and a recorder service started on a router."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from protocol.bus import Bus
from recorder import standalone
from support.processes import ROOT


def run_cli(*argv: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env=env,
    )


def start_recorder(endpoint: str, bus: Bus, run_id: str, output: Path, *extra: str) -> subprocess.Popen:
    """A recorder process on the router at ``endpoint``, up (its liveliness token seen); ``extra``: more of its
    command line (``"--set", "flush_interval_s=0.05"``)."""
    return standalone.start_recorder(
        endpoint=endpoint, bus=bus, run_id=run_id, output=output, extra_args=extra, cwd=ROOT, stdout=subprocess.PIPE
    )
