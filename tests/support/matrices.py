"""Matrix files written for a test, the finished rows of a results database, and processes found by command line."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path


def write_matrix(folder: Path, body: str) -> Path:
    path = folder / "m.yaml"
    path.write_text(body)
    return path


def processes_with(text: str) -> list[int]:
    """Pids of live processes whose command line contains ``text`` (real /proc, no mocks)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().split(") ", 1)[1][0]
        except OSError:
            continue
        if text in cmdline and state != "Z" and int(entry.name) != os.getpid():
            pids.append(int(entry.name))
    return pids


def finished_rows(database: Path) -> list[tuple]:
    if not database.exists():
        return []
    try:
        with sqlite3.connect(database, timeout=5) as db:
            return db.execute("SELECT key, run_id, started_at, status FROM episodes ORDER BY idx").fetchall()
    except sqlite3.OperationalError:  # created but no table yet
        return []
