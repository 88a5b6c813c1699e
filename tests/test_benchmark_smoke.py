"""Benchmarks are not timed in CI, but they must still run: each one's smallest form, end to end."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_report_statistics_benchmark_prints_its_table():
    result = subprocess.run(
        [sys.executable, "benchmarks/report_statistics.py", "--episodes", "40", "--brains", "2", "--seeds", "2"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    assert rows[0] == "| report of 40 episodes (2 brains x 2 seeds) | seconds |"
    assert any(row.startswith("| with it (2,000 resamples per interval) |") for row in rows)
