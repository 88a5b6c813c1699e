"""A matrix's results: one SQLite database in the output folder, one row per finished episode.

Each row is committed the moment its episode ends (SQLite in WAL mode, ``synchronous=FULL``), so an orchestrator
killed with SIGKILL loses only the episodes that were still running; ``--resume`` runs exactly those again.

Status of a row:
    ``done``   the episode ran and was scored, whatever the brain did (a crash is a result, not a failure);
    ``failed`` the stack failed the episode (a process died, no score in time, the simulator refused it):
               ``failure_kind`` says which (a ``FailureKind``, ``orchestrator/stack/failures.py``) and
               ``failure_detail`` what a person reads (stored apart, so reading a row never parses text). A score is
               kept when the scorer still produced one (a brain killed mid-episode ends it with ``brain_lost``).

The stored schema carries a version (SQLite's ``user_version``, :data:`SCHEMA_VERSION`), so that results written by
an earlier drivebench stay readable: opening a file upgrades it to this version (:data:`_UPGRADES`), and a file
written by a later drivebench is refused in one line rather than misread. Episode specs and scores are stored as
JSON of their msgspec structs: a field added to them needs a default, or an upgrade step here that fills it in;
``tests/test_results_schema.py`` reads a file written by drivebench 0.1.0 (``tests/fixtures/results-0.1.0``) and
fails when neither was done.
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orchestrator.matrix.plan import BrainEntry, PlannedEpisode
from orchestrator.stack.failures import Failure, FailureKind
from protocol import codec
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EpisodeScore

DATABASE_NAME = "results.sqlite"
# The stored schema's version. 0: drivebench 0.1.0 and earlier (no version stored); 1: versioned (issue 39);
# 2: a failure's kind and detail in their own columns (issue 41; 0 and 1 stored one "<kind>: <detail>" text).
SCHEMA_VERSION = 2
# A fact the runner stores for the report: the variation label of the matrix's first episode (the baseline column).
BASELINE_FACT = "baseline_variation"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS matrix (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS episodes (
    key          TEXT PRIMARY KEY,   -- stable id of the planned episode (what --resume compares)
    idx          INTEGER NOT NULL,   -- position in the matrix's expansion
    brain        TEXT NOT NULL,      -- the brain's label in the matrix (unique per brain entry)
    circuit      TEXT NOT NULL,
    variation    TEXT NOT NULL,      -- label, e.g. "line=white,walls=off" ("default" when none)
    perturbation TEXT NOT NULL,      -- label, e.g. "salt_pepper=0.2" ("none" when none)
    repetition   INTEGER NOT NULL,
    spec_json    TEXT NOT NULL,      -- the EpisodeSpec as JSON
    brain_json   TEXT NOT NULL,      -- the brain entry: name, weights, options
    status       TEXT NOT NULL CHECK (status IN ('done', 'failed')),
    reason       TEXT,               -- EndReason of the score, when scored
    failure_kind   TEXT,             -- the FailureKind's value when failed
    failure_detail TEXT,             -- the failure's detail, for a person, when failed
    score_json   TEXT,               -- the EpisodeScore as JSON, when scored
    run_id       TEXT NOT NULL,
    started_at   REAL NOT NULL,      -- wall clock, seconds since the epoch
    ended_at     REAL NOT NULL,
    recording    TEXT,               -- MCAP file, relative to the output folder, when recorded
    trajectory   TEXT,               -- .npz file of poses and live progress, relative to the output folder
    logs         TEXT,               -- folder of the episode's process logs, relative to the output folder
    node         TEXT,               -- where it ran: the host name, or "<ip>/<ray node id>" on a Ray cluster
    lost_attempts TEXT               -- JSON list of earlier attempts lost with their node ({"node", "error"})
);
"""
# Columns added after the first release: a results file written before them gets them (NULL) when opened.
_ADDED_COLUMNS = {"node": "TEXT", "lost_attempts": "TEXT"}


def _add_columns(db: sqlite3.Connection) -> None:
    have = {row[1] for row in db.execute("PRAGMA table_info(episodes)")}
    for name, kind in _ADDED_COLUMNS.items():
        if name not in have:
            db.execute(f"ALTER TABLE episodes ADD COLUMN {name} {kind}")


def _split_failures(db: sqlite3.Connection) -> None:
    """Version 1 to 2: the failure's kind and detail get their own columns. Schemas 0 and 1 stored one
    ``<kind>: <detail>`` text; this step is the one place such stored text is split (old rows only: nothing else
    reads it, and the old column is dropped once its rows are split)."""
    db.execute("ALTER TABLE episodes ADD COLUMN failure_kind TEXT")
    db.execute("ALTER TABLE episodes ADD COLUMN failure_detail TEXT")
    rows = db.execute("SELECT key, failure FROM episodes WHERE failure IS NOT NULL").fetchall()
    for key, text in rows:
        kind, _, detail = text.partition(": ")
        db.execute("UPDATE episodes SET failure_kind = ?, failure_detail = ? WHERE key = ?", (kind, detail, key))
    db.execute("ALTER TABLE episodes DROP COLUMN failure")


# The step that takes a file of version N to N + 1, applied in order from the file's version. A new file is made at
# SCHEMA_VERSION by _SCHEMA and takes no step.
_UPGRADES = {0: _add_columns, 1: _split_failures}
_COLUMNS = (
    "key, idx, brain, circuit, variation, perturbation, repetition, spec_json, brain_json, status, reason, "
    "failure_kind, failure_detail, score_json, run_id, started_at, ended_at, recording, trajectory, logs, node, "
    "lost_attempts"
)


@dataclass(frozen=True, kw_only=True)
class LostAttempt:
    """An attempt at an episode lost with its node or worker process (Ray): where (``node``, None when the error
    does not say) and the error, in one line. Stored in the row as ``{"node", "error"}``."""

    node: str | None
    error: str

    def to_dict(self) -> dict[str, str | None]:
        return {"node": self.node, "error": self.error}

    @classmethod
    def from_dict(cls, row: dict) -> LostAttempt:
        return cls(node=row.get("node"), error=row["error"])


@dataclass(frozen=True)
class EpisodeResult:
    """One finished episode as stored. Paths are relative to the output folder."""

    key: str
    index: int
    brain: str
    circuit: str
    variation: str
    perturbation: str
    repetition: int
    spec: EpisodeSpec
    brain_entry: BrainEntry
    status: str
    run_id: str
    started_at: float
    ended_at: float
    reason: str | None = None
    failure: Failure | None = None
    score: EpisodeScore | None = None
    recording: str | None = None
    trajectory: str | None = None
    logs: str | None = None
    node: str | None = None  # where it ran (None in results written before this was recorded)
    lost_attempts: tuple[LostAttempt, ...] = ()  # earlier attempts whose node died, never results

    @classmethod
    def of(cls, episode: PlannedEpisode, **outcome: Any) -> EpisodeResult:
        """The result of a planned episode: what the plan says of it (key, index, brain, circuit, variation,
        perturbation, repetition, spec) is taken from ``episode`` here, in one place; ``outcome`` is the rest."""
        return cls(
            key=episode.key,
            index=episode.index,
            brain=episode.brain.label,
            circuit=episode.circuit,
            variation=episode.variation,
            perturbation=episode.perturbation,
            repetition=episode.repetition,
            spec=episode.spec,
            brain_entry=episode.brain,
            **outcome,
        )

    @property
    def wall_s(self) -> float:
        return self.ended_at - self.started_at

    @property
    def failure_kind(self) -> FailureKind | None:
        return self.failure.kind if self.failure else None


class ResultsError(RuntimeError):
    """The results database cannot be used (not a drivebench database, or damaged); one line, names the file."""


class ResultStore:
    """Results of one output folder. Safe to open from one writer and any number of readers.

    ``ResultStore(folder)`` is the writer's store: it makes the file (or upgrades an older one in place) and switches
    it to WAL mode. A reader that must leave the file as it is (a report of committed results, a power plan from a
    pilot's folder) opens it with :meth:`read_only` instead.
    """

    def __init__(self, folder: Path, *, create: bool = True):
        self.path = Path(folder) / DATABASE_NAME
        if not create:
            self._require_file(folder)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # Workers record from their own threads; the runner serialises the writes with a lock.
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")  # a row committed is a row on disk, SIGKILL or not
            self._upgrade()
        except sqlite3.DatabaseError as error:
            raise ResultsError(f"{self.path}: not a usable results database ({error})") from None

    @classmethod
    def read_only(cls, folder: Path) -> ResultStore:
        """``folder``'s results, read without writing a byte of its file.

        The file is copied into memory (SQLite's backup: a consistent snapshot, even while a matrix still writes it)
        and an older schema is upgraded in the copy, so a results file committed to git stays the bytes its study
        wrote: opening it as the writer does would switch its journal mode and upgrade it in place.
        """
        store = cls.__new__(cls)
        store.path = Path(folder) / DATABASE_NAME
        store._require_file(folder)
        # With no -wal file beside it, no writer holds the file and every committed row is in it: read it as
        # immutable, which creates no -wal or -shm either. With one, a matrix may still be writing: read the WAL too.
        idle = not store.path.with_name(f"{DATABASE_NAME}-wal").exists()
        try:
            source = sqlite3.connect(
                f"{store.path.resolve().as_uri()}?{'immutable=1' if idle else 'mode=ro'}", uri=True, timeout=30.0
            )
            try:
                store._db = sqlite3.connect(":memory:", isolation_level=None, check_same_thread=False)
                source.backup(store._db)
            finally:
                source.close()
            store._upgrade()
        except sqlite3.DatabaseError as error:
            raise ResultsError(f"{store.path}: not a usable results database ({error})") from None
        return store

    def _require_file(self, folder: Path) -> None:
        if not self.path.is_file():
            raise ResultsError(f"{self.path}: no results database (run `drivebench matrix FILE -o {folder}` first)")

    @property
    def schema_version(self) -> int:
        return int(self._db.execute("PRAGMA user_version").fetchone()[0])

    def _upgrade(self) -> None:
        """The file at :data:`SCHEMA_VERSION` (made when new, upgraded step by step when older), or a
        :class:`ResultsError` for a file a later drivebench wrote."""
        if self._checked_version() == SCHEMA_VERSION:
            return
        # One transaction that holds the write lock: a file is upgraded whole or not at all, and by one opener (the
        # version is read again under the lock, since another may have upgraded it meanwhile).
        self._db.execute("BEGIN IMMEDIATE")
        try:
            self._upgrade_locked(self._checked_version())
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def _checked_version(self) -> int:
        version = self.schema_version
        if version > SCHEMA_VERSION:
            raise ResultsError(
                f"{self.path}: written by a newer drivebench (results schema {version}; this one reads schemas up "
                f"to {SCHEMA_VERSION}): upgrade drivebench to read it"
            )
        return version

    def _upgrade_locked(self, version: int) -> None:
        if self._db.execute("SELECT 1 FROM sqlite_master WHERE name = 'episodes'").fetchone() is None:
            for statement in _SCHEMA.split(";"):  # one by one: executescript would end the transaction
                self._db.execute(statement)
        else:
            for step in range(version, SCHEMA_VERSION):
                _UPGRADES[step](self._db)
        # PRAGMA takes no bound parameter; the value is this module's integer constant.
        self._db.execute(f"PRAGMA user_version = {SCHEMA_VERSION:d}")

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- matrix facts (name, source text, ...) --

    def set_fact(self, key: str, value: Any) -> None:
        self._db.execute("INSERT OR REPLACE INTO matrix (key, value) VALUES (?, ?)", (key, json.dumps(value)))

    def fact(self, key: str, default: Any = None) -> Any:
        row = self._db.execute("SELECT value FROM matrix WHERE key = ?", (key,)).fetchone()
        return json.loads(row[0]) if row else default

    # -- episodes --

    def record(self, result: EpisodeResult) -> None:
        """Store (or replace) one finished episode; committed before this returns."""
        self._db.execute(
            f"INSERT OR REPLACE INTO episodes ({_COLUMNS}) VALUES ({', '.join('?' * 22)})",
            (
                result.key,
                result.index,
                result.brain,
                result.circuit,
                result.variation,
                result.perturbation,
                result.repetition,
                codec.to_json(result.spec),
                json.dumps(result.brain_entry.to_dict()),
                result.status,
                result.reason,
                None if result.failure is None else result.failure.kind.value,
                None if result.failure is None else result.failure.detail,
                codec.to_json(result.score) if result.score is not None else None,
                result.run_id,
                result.started_at,
                result.ended_at,
                result.recording,
                result.trajectory,
                result.logs,
                result.node,
                json.dumps([attempt.to_dict() for attempt in result.lost_attempts]) if result.lost_attempts else None,
            ),
        )

    def finished_keys(self, *, include_failed: bool = True) -> set[str]:
        query = "SELECT key FROM episodes" + ("" if include_failed else " WHERE status = 'done'")
        return {row[0] for row in self._db.execute(query)}

    def results(self) -> list[EpisodeResult]:
        """Every stored episode, in matrix order."""
        rows = self._db.execute(f"SELECT {_COLUMNS} FROM episodes ORDER BY idx").fetchall()
        return [self._result(row) for row in rows]

    def _result(self, row: tuple) -> EpisodeResult:
        (
            key,
            index,
            brain,
            circuit,
            variation,
            perturbation,
            repetition,
            spec_json,
            brain_json,
            status,
            reason,
            failure_kind,
            failure_detail,
            score_json,
            run_id,
            started_at,
            ended_at,
            recording,
            trajectory,
            logs,
            node,
            lost_attempts,
        ) = row
        try:
            spec = _from_json(spec_json, EpisodeSpec)
            score = _from_json(score_json, EpisodeScore) if score_json else None
        except ValueError as error:
            raise ResultsError(f"{self.path}: episode {key!r} is damaged ({error})") from None
        return EpisodeResult(
            key=key,
            index=index,
            brain=brain,
            circuit=circuit,
            variation=variation,
            perturbation=perturbation,
            repetition=repetition,
            spec=spec,
            brain_entry=BrainEntry.from_dict(json.loads(brain_json), label=brain),
            status=status,
            run_id=run_id,
            started_at=started_at,
            ended_at=ended_at,
            reason=reason,
            failure=_failure(failure_kind, failure_detail),
            score=score,
            recording=recording,
            trajectory=trajectory,
            logs=logs,
            node=node,
            lost_attempts=tuple(map(LostAttempt.from_dict, json.loads(lost_attempts))) if lost_attempts else (),
        )


def _failure(kind: str | None, detail: str | None) -> Failure | None:
    """The stored failure, read from its two columns; a kind this drivebench does not know (a later one wrote it)
    is ``error``, with the unknown kind kept in front of the detail for the person reading it."""
    if kind is None:
        return None
    if kind in FailureKind._value2member_map_:
        return Failure(FailureKind(kind), detail or "")
    return Failure(FailureKind.ERROR, f"{kind}: {detail}" if detail else kind)


def _from_json(text: str, message_type: type):
    import msgspec

    try:
        return msgspec.json.decode(text, type=message_type)
    except (msgspec.DecodeError, msgspec.ValidationError) as error:
        raise ValueError(str(error)) from None
