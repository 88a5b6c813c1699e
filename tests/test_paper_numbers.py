"""Every number docs/paper.md quotes from a study is what the study's committed results give (issue 39).

The studies' raw results are committed under experiments/results/; orchestrator/report/studies.py writes each
study's block of docs/paper.md from them, and this test regenerates the blocks and compares them with the page.
"""

from __future__ import annotations

import re

import pytest

from orchestrator.report import studies


@pytest.mark.parametrize("study", studies.STUDIES, ids=lambda study: study.name)
def test_the_page_quotes_what_the_committed_results_give(study, tmp_path):
    assert (study.results_dir / "results.sqlite").is_file(), f"{study.results_dir}: the study's results are missing"
    assert (study.results_dir / "episodes.csv").is_file(), f"{study.results_dir}: the study's episodes.csv is missing"
    studies.check(study, scratch=tmp_path)
    assert study.profile_png.is_file()


@pytest.mark.parametrize("study", studies.STUDIES, ids=lambda study: study.name)
def test_a_number_changed_by_hand_is_caught(study, tmp_path):
    page = studies.PAPER.read_text(encoding="utf-8")
    block = studies.current_block(study, page)
    number = re.search(r"\d\.\d\d \[", block)
    assert number, "the block quotes no estimate with an interval"
    digit = block[number.start()]
    edited = block[: number.start()] + ("1" if digit == "0" else "0") + block[number.start() + 1 :]
    with pytest.raises(studies.StaleBlock, match="differs from what"):
        studies.check(study, scratch=tmp_path, page=page.replace(block, edited))


def test_reading_a_study_leaves_its_committed_file_untouched(tmp_path):
    study = studies.STUDIES[0]
    database = study.results_dir / "results.sqlite"
    before = database.read_bytes()
    studies.study_block(study, scratch=tmp_path)
    assert database.read_bytes() == before
    assert not database.with_name("results.sqlite-wal").exists()
