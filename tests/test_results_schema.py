"""Results written by an earlier drivebench stay readable (issue 39): the stored schema is versioned, a file of
drivebench 0.1.0 (tests/fixtures/results-0.1.0, written by that release) is upgraded and reported, and a file of a
later drivebench is refused in one line. Since schema 2 (issue 41) a failure's kind and detail are stored apart:
failures stored by schemas 0 and 1 as one ``<kind>: <detail>`` text read back with their kinds."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pytest

from orchestrator.cli import main
from orchestrator.matrix.results import SCHEMA_VERSION, EpisodeResult, ResultsError, ResultStore
from orchestrator.stack.failures import Failure, FailureKind

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "results-0.1.0"


def copy_of_fixture(tmp_path: Path) -> Path:
    folder = tmp_path / "old"
    shutil.copytree(FIXTURE, folder)  # opening a results file upgrades it in place: never the committed one
    return folder


# Failures as schemas 0 and 1 stored them, one text per row: a known kind whose detail holds ": ", and a kind this
# drivebench does not know (a later one wrote it), which reads as an error with the whole text kept.
OLD_FAILURES = {
    0: "brain_died: brain 'tiny' exited with code -9; its last log line: MemoryError: out of memory",
    1: "cosmic_ray: bit flipped",
    2: "wall_timeout: no score within 120 s",
}
READ_BACK = {
    0: Failure(
        FailureKind.BRAIN_DIED, "brain 'tiny' exited with code -9; its last log line: MemoryError: out of memory"
    ),
    1: Failure(FailureKind.ERROR, "cosmic_ray: bit flipped"),
    2: Failure(FailureKind.WALL_TIMEOUT, "no score within 120 s"),
}


def old_results_with_failures(tmp_path: Path, *, version: int) -> Path:
    """The 0.1.0 fixture as a drivebench of results schema ``version`` (0 or 1) would have stored it with three
    failed episodes: schema 1 is schema 0 with the columns node and lost_attempts and its version stored."""
    folder = copy_of_fixture(tmp_path)
    with sqlite3.connect(folder / "results.sqlite") as db:
        columns = {row[1] for row in db.execute("PRAGMA table_info(episodes)")}
        assert "failure" in columns and "failure_kind" not in columns  # the one-text column, as they stored it
        if version == 1:
            for name in {"node", "lost_attempts"} - columns:
                db.execute(f"ALTER TABLE episodes ADD COLUMN {name} TEXT")
            db.execute("PRAGMA user_version = 1")
        for index, text in OLD_FAILURES.items():
            db.execute("UPDATE episodes SET status = 'failed', failure = ? WHERE idx = ?", (text, index))
    return folder


@pytest.mark.parametrize("version", [0, 1])
def test_failures_stored_as_one_text_by_an_earlier_schema_read_back_with_their_kinds(tmp_path, version):
    folder = old_results_with_failures(tmp_path, version=version)
    with ResultStore(folder, create=False) as store:
        failures = {r.index: r.failure for r in store.results() if r.status == "failed"}
        assert store.schema_version == SCHEMA_VERSION
    assert failures == READ_BACK
    with sqlite3.connect(folder / "results.sqlite") as db:  # upgraded in place: the one-text column is gone
        columns = {row[1] for row in db.execute("PRAGMA table_info(episodes)")}
    assert {"failure_kind", "failure_detail"} <= columns and "failure" not in columns


def test_a_failure_whose_detail_holds_a_colon_round_trips_as_kind_and_detail(tmp_path):
    with ResultStore(copy_of_fixture(tmp_path), create=False) as old:
        result = old.results()[0]
    failure = Failure(FailureKind.SCORER_DIED, "scorer exited: code 1: KeyError: 'lap'")
    failed = EpisodeResult(**{**vars(result), "status": "failed", "failure": failure})
    with ResultStore(tmp_path / "new") as store:
        store.record(failed)
        assert store.results()[0].failure == failure
    with sqlite3.connect(tmp_path / "new" / "results.sqlite") as db:
        stored = db.execute("SELECT failure_kind, failure_detail FROM episodes").fetchone()
    assert stored == ("scorer_died", "scorer exited: code 1: KeyError: 'lap'")  # apart, as written


def test_results_of_drivebench_0_1_0_are_read_and_upgraded(tmp_path):
    folder = copy_of_fixture(tmp_path)
    with sqlite3.connect(folder / "results.sqlite") as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 0  # as released: no version stored
    with ResultStore(folder, create=False) as store:
        results = store.results()
        assert store.schema_version == SCHEMA_VERSION
    assert len(results) == 12 and all(r.score is not None and r.status == "done" for r in results)
    assert {r.brain_entry.group for r in results} == {"", "tiny"}


def test_drivebench_report_reads_results_of_drivebench_0_1_0(tmp_path, capsys):
    folder = copy_of_fixture(tmp_path)
    assert main(["report", str(folder), "-o", str(tmp_path / "report")]) == 0, capsys.readouterr().err
    report = (tmp_path / "report" / "report.md").read_text()
    comparison = report.split("## Comparison with intervals", 1)[1].split("\n## ", 1)[0]
    # Two parts that differ only in their name: 2 parts x 2 circuits = 4 conditions, every one kept.
    assert "| tiny | 2 (seeds 0, 1) | 4 |" in comparison, comparison


@pytest.mark.parametrize("version", [0, 1])
def test_drivebench_report_lists_the_failures_an_earlier_schema_stored(tmp_path, capsys, version):
    folder = old_results_with_failures(tmp_path, version=version)
    assert main(["report", str(folder), "-o", str(tmp_path / "report")]) == 0, capsys.readouterr().err
    report = (tmp_path / "report" / "report.md").read_text()
    for failure in READ_BACK.values():
        assert str(failure).replace("|", "\\|") in report, str(failure)
    # The main table's failures column counts them by kind (kinds read from the store, never from the text).
    assert "| 1/2 | brain_died 1 |" in report and "| 1/2 | wall_timeout 1 |" in report, report


def test_a_file_of_a_later_drivebench_is_refused_in_one_line(tmp_path, capsys):
    folder = copy_of_fixture(tmp_path)
    with sqlite3.connect(folder / "results.sqlite") as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    assert main(["report", str(folder)]) == 2
    error = capsys.readouterr().err.strip()
    assert "newer drivebench" in error and f"results schema {SCHEMA_VERSION + 1}" in error, error
    assert "\n" not in error and "Traceback" not in error


def test_a_new_results_file_carries_the_current_version(tmp_path):
    with ResultStore(tmp_path) as store:
        assert store.schema_version == SCHEMA_VERSION


def _current_schema_in_rollback_mode(tmp_path: Path) -> Path:
    """The fixture as a study commits its results: upgraded to this schema, then one file (no WAL beside it)."""
    folder = copy_of_fixture(tmp_path)
    ResultStore(folder, create=False).close()
    with sqlite3.connect(folder / "results.sqlite") as db:
        db.execute("PRAGMA journal_mode=DELETE")
    return folder


@pytest.mark.parametrize("schema", ["0.1.0", "current"])
def test_a_report_and_a_power_plan_leave_the_results_file_as_it_was(tmp_path, capsys, schema):
    from orchestrator.report.power import spread_of_results

    folder = copy_of_fixture(tmp_path) if schema == "0.1.0" else _current_schema_in_rollback_mode(tmp_path)
    database = folder / "results.sqlite"
    before = database.read_bytes()
    assert main(["report", str(folder), "-o", str(tmp_path / "report")]) == 0, capsys.readouterr().err
    assert spread_of_results(folder).run_sd > 0
    # Committed results (experiments/results/) must stay the bytes their study wrote: opening the file as the
    # writer does switched it to WAL mode and upgraded it in place, and git saw it changed.
    assert database.read_bytes() == before
    assert sorted(path.name for path in folder.iterdir()) == ["results.sqlite"]


def test_a_reader_sees_what_a_writer_still_holding_the_file_has_committed(tmp_path):
    with ResultStore(tmp_path) as writer:
        writer.set_fact("name", "running")
        with ResultStore.read_only(tmp_path) as reader:
            assert reader.fact("name") == "running" and reader.schema_version == SCHEMA_VERSION


def test_a_reader_of_a_damaged_file_gets_one_line(tmp_path):
    (tmp_path / "results.sqlite").write_bytes(b"not a database, only bytes" * 100)
    with pytest.raises(ResultsError, match=r"results.sqlite: not a usable results database"):
        ResultStore.read_only(tmp_path)
