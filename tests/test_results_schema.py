"""Results written by an earlier drivebench stay readable (issue 39): the stored schema is versioned, a file of
drivebench 0.1.0 (tests/fixtures/results-0.1.0, written by that release) is upgraded and reported, and a file of a
later drivebench is refused in one line."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

from orchestrator.cli import main
from orchestrator.matrix.results import SCHEMA_VERSION, ResultStore

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "results-0.1.0"


def copy_of_fixture(tmp_path: Path) -> Path:
    folder = tmp_path / "old"
    shutil.copytree(FIXTURE, folder)  # opening a results file upgrades it in place: never the committed one
    return folder


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
