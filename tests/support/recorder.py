"""The recorder as real processes: its CLI, and a recorder service started on a router."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from protocol import keys
from protocol.bus import Bus
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
    watch = bus.watch_alive(keys.alive(run_id, "recorder", "recorder"))
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "recorder",
            "--router",
            endpoint,
            "--run-id",
            run_id,
            "--set",
            f"output={json.dumps(str(output))}",
            *extra,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    missing = watch.wait_for({keys.alive(run_id, "recorder", "recorder")}, timeout_s=30)
    watch.close()
    assert not missing, f"recorder did not come up: {process.poll()}"
    return process
