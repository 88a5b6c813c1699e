"""The dataset CLI as a user runs it (a real process), and small real recordings to build datasets from."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import msgspec

from recorder.writer import RecordingWriter
from support.processes import ROOT
from support.recordings import episode_stream


def record(path: Path, run_id: str, *, episodes: int = 2, frames: int = 12) -> Path:
    """A recording of ``episodes`` episodes of ``frames`` answered frames each."""
    with RecordingWriter(path, views=False) as writer:
        writer.add_metadata("drivebench.run", {"run_id": run_id})
        for episode in range(episodes):
            for item in episode_stream(run_id, episode, frames):
                # The writer places a message by its header's stamp: an event's is its log time, as the simulator's.
                header = msgspec.structs.replace(item.message.header, stamp_ns=item.log_time_ns)
                writer.write(item.key, msgspec.structs.replace(item.message, header=header))
    return path


def drivebench(*argv: str | Path, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
    )


def build(*argv: str | Path, cwd: Path = ROOT, size: str = "40x20") -> subprocess.CompletedProcess:
    return drivebench("dataset", "build", *argv, "--size", size, cwd=cwd)


def one_line_error(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    return result.stderr
