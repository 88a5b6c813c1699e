"""A recorder process of its own on a router, without a stack: ``python -m recorder --router ENDPOINT --run-id RUN
--set output=FILE``, started and waited for until its liveliness token is up. Tests and the recording benchmark
record this way; a stack's recorder is started by the launcher from the process graph instead."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import IO

from protocol import keys
from protocol.bus import Bus

UP_TIMEOUT_S = 30.0  # a recorder imports MCAP and protobuf before it declares itself: seconds on a loaded machine


class RecorderStartError(RuntimeError):
    """The recorder did not declare its liveliness token in time (it died, or is still starting)."""


def start_recorder(
    *,
    endpoint: str,
    bus: Bus,
    run_id: str,
    output: Path,
    extra_args: tuple[str, ...] = (),
    cwd: Path | None = None,
    stdout: int | IO | None = subprocess.DEVNULL,
    timeout_s: float = UP_TIMEOUT_S,
) -> subprocess.Popen:
    """Start a recorder of ``run_id`` into ``output`` on the router at ``endpoint`` and return once its liveliness
    token is on ``bus``. extra_args: more of its command line (``("--set", "image_format=jpeg")``).
    stdout: where its output goes (stderr goes with it). :class:`RecorderStartError` when it is not up within
    ``timeout_s``; the process is left to the caller (its exit code says why)."""
    token = keys.alive(run_id, "recorder", "recorder")
    watch = bus.watch_alive(token)
    argv = [sys.executable, "-m", "recorder", "--router", endpoint, "--run-id", run_id]
    argv += ["--set", f"output={json.dumps(str(output))}", *extra_args]
    try:
        process = subprocess.Popen(argv, cwd=cwd, stdout=stdout, stderr=subprocess.STDOUT, text=True)
        if watch.wait_for({token}, timeout_s=timeout_s):
            raise RecorderStartError(f"recorder of run {run_id!r} did not come up in {timeout_s:g} s: {process.poll()}")
    finally:
        watch.close()
    return process
