"""The submissions of a challenge and their states, in ``DIR/board.sqlite`` (schema versioned).

A submission moves ``queued -> checking -> running -> scored | rejected`` (``error`` when the server itself could
not evaluate it). Every claim of a queued submission increments its ``attempt``; a worker writes its outcome only
for the attempt it claimed, so an evaluation left behind by a server that was killed can never score a submission a
second time. On start, :meth:`BoardStore.requeue_interrupted` puts what a killed server left checking or running
back in the queue.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

SCHEMA_VERSION = 1
STORE_FILE = "board.sqlite"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS submissions (
    id          TEXT PRIMARY KEY,    -- random hex: a submission's page address
    seq         INTEGER NOT NULL,    -- submission order (the queue's order)
    name        TEXT NOT NULL,       -- who submitted, as given
    kind        TEXT NOT NULL,       -- python, wheel, onnx, behavior_metrics (intake.Kind)
    filename    TEXT NOT NULL,       -- the uploaded file's name as given
    state       TEXT NOT NULL,       -- State
    reason      TEXT,                -- Rejection of a rejected one
    detail      TEXT,                -- one line a person reads (never parsed)
    attempt     INTEGER NOT NULL DEFAULT 0,
    created_at  REAL NOT NULL,
    updated_at  REAL NOT NULL,
    scores_json TEXT,                -- scoring.Scores as JSON (public part of it only is served)
    config_sha256 TEXT               -- digest of the exact matrix text that produced the scores
);
"""


class State(StrEnum):
    QUEUED = "queued"
    CHECKING = "checking"  # the brain contract (drivebench brains check)
    RUNNING = "running"  # the episodes
    SCORED = "scored"
    REJECTED = "rejected"
    ERROR = "error"  # the server could not evaluate it (its stack failed): not the brain's fault


FINAL_STATES = (State.SCORED, State.REJECTED, State.ERROR)


class Rejection(StrEnum):
    """Why a submission was rejected, typed."""

    DOES_NOT_LOAD = "does_not_load"
    BREAKS_CONTRACT = "breaks_contract"
    CRASHED = "crashed"
    TOO_SLOW = "too_slow"
    EXCEEDED_LIMIT = "exceeded_limit"
    SANDBOX_VIOLATION = "sandbox_violation"


class StoreError(RuntimeError):
    """The data folder holds a store this drivebench cannot read (a newer schema)."""


@dataclass(frozen=True)
class Submission:
    id: str
    seq: int
    name: str
    kind: str
    filename: str
    state: State
    attempt: int
    created_at: float
    updated_at: float
    reason: str | None = None
    detail: str | None = None
    scores: dict[str, Any] | None = None
    config_sha256: str | None = None


def new_id() -> str:
    return uuid.uuid4().hex[:16]


class BoardStore:
    """One connection shared by the server's threads, every statement under one lock (SQLite serialises anyway)."""

    def __init__(self, data_dir: Path):
        self.path = Path(data_dir) / STORE_FILE
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")  # a reader never waits for the worker's commit
        self._lock = threading.Lock()
        with self._lock:
            self._db.executescript(_SCHEMA)
            self._check_version()

    def _check_version(self) -> None:
        row = self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        if row is None:
            self._db.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) > SCHEMA_VERSION:
            raise StoreError(f"{self.path}: schema version {row[0]} is newer than this drivebench's {SCHEMA_VERSION}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def add(self, *, submission_id: str, name: str, kind: str, filename: str) -> Submission:
        """Queue a submission whose files are in place (a worker may claim it at once)."""
        now = time.time()
        with self._lock:
            seq = self._db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM submissions").fetchone()[0]
            self._db.execute(
                "INSERT INTO submissions (id, seq, name, kind, filename, state, created_at, updated_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (submission_id, seq, name, kind, filename, State.QUEUED, now, now),
            )
        submission = self.get(submission_id)
        assert submission is not None
        return submission

    def get(self, submission_id: str) -> Submission | None:
        with self._lock:
            row = self._db.execute(f"SELECT {_COLUMNS} FROM submissions WHERE id = ?", (submission_id,)).fetchone()
        return _submission(row) if row else None

    def all(self) -> list[Submission]:
        with self._lock:
            rows = self._db.execute(f"SELECT {_COLUMNS} FROM submissions ORDER BY seq").fetchall()
        return [_submission(row) for row in rows]

    def claim(self) -> Submission | None:
        """The oldest queued submission, now checking under a new attempt; None when the queue is empty."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            row = self._db.execute("SELECT id FROM submissions WHERE state = ? ORDER BY seq LIMIT 1", (State.QUEUED,))
            found = row.fetchone()
            if found is not None:
                self._db.execute(
                    "UPDATE submissions SET state = ?, attempt = attempt + 1, updated_at = ? WHERE id = ?",
                    (State.CHECKING, time.time(), found[0]),
                )
            self._db.execute("COMMIT")
        return self.get(found[0]) if found else None

    def advance(self, submission: Submission, state: State, **outcome: Any) -> bool:
        """Move ``submission`` (as claimed: its attempt) to ``state`` with ``outcome`` (reason, detail, scores,
        config_sha256); False, and nothing written, when that attempt is no longer the submission's."""
        scores = outcome.pop("scores", None)
        values = {**outcome, "scores_json": None if scores is None else json.dumps(scores)}
        sets = ", ".join(f"{column} = ?" for column in values)
        with self._lock:
            cursor = self._db.execute(
                f"UPDATE submissions SET state = ?, updated_at = ?, {sets} WHERE id = ? AND attempt = ? "
                "AND state NOT IN (?, ?, ?)",
                (state, time.time(), *values.values(), submission.id, submission.attempt, *FINAL_STATES),
            )
        return cursor.rowcount == 1

    def requeue_interrupted(self) -> int:
        """Put back in the queue what a server that stopped left checking or running; how many."""
        with self._lock:
            cursor = self._db.execute(
                "UPDATE submissions SET state = ?, updated_at = ? WHERE state IN (?, ?)",
                (State.QUEUED, time.time(), State.CHECKING, State.RUNNING),
            )
        return cursor.rowcount


_COLUMNS = (
    "id, seq, name, kind, filename, state, attempt, created_at, updated_at, reason, detail, scores_json, config_sha256"
)


def _submission(row: tuple) -> Submission:
    (submission_id, seq, name, kind, filename, state, attempt, created_at, updated_at, reason, detail) = row[:11]
    scores_json, config_sha256 = row[11:]
    return Submission(
        id=submission_id,
        seq=seq,
        name=name,
        kind=kind,
        filename=filename,
        state=State(state),
        attempt=attempt,
        created_at=created_at,
        updated_at=updated_at,
        reason=reason,
        detail=detail,
        scores=json.loads(scores_json) if scores_json else None,
        config_sha256=config_sha256,
    )
