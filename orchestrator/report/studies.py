"""The studies' answers in docs/paper.md, regenerated from their committed results (issue 39).

Each study's raw results are committed under ``experiments/results/<study>/`` (``results.sqlite``, ``episodes.csv``).
docs/paper.md quotes its "Comparison with intervals" between two markers; this module writes that block from the
committed results, and a test (tests/test_paper_numbers.py) checks that the page still says what they give::

    python -m orchestrator.report.studies --write     # after committing a study's new results
    python -m orchestrator.report.studies --check     # what the test runs: exit 1 when a block is stale

The results file is read with ``ResultStore.read_only``, never in place: the committed file must stay the bytes its
study wrote.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from orchestrator.matrix.results import ResultStore
from orchestrator.report.comparison import comparison_section
from orchestrator.report.document import Plot, Section, render_markdown

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "docs" / "paper.md"


@dataclass(frozen=True)
class Study:
    """One study whose answer docs/paper.md quotes: its committed results and the picture the page shows."""

    name: str
    results_dir: Path
    profile_png: Path  # the performance profile, beside the page

    @property
    def begin_marker(self) -> str:
        return (
            f"<!-- generated from experiments/results/{self.name} by `python -m orchestrator.report.studies --write`;"
            " tests/test_paper_numbers.py checks it: do not edit by hand -->"
        )

    @property
    def end_marker(self) -> str:
        return f"<!-- end of the block generated from experiments/results/{self.name} -->"


STUDIES = (
    Study(
        name="memory_study",
        results_dir=ROOT / "experiments" / "results" / "memory_study",
        profile_png=ROOT / "docs" / "memory_study_full_profile.png",
    ),
    Study(
        name="randomised_full_pilot",
        results_dir=ROOT / "experiments" / "results" / "randomised_full_pilot",
        profile_png=ROOT / "docs" / "randomised_full_pilot_profile.png",
    ),
    Study(
        name="randomised_full",
        results_dir=ROOT / "experiments" / "results" / "randomised_full",
        profile_png=ROOT / "docs" / "randomised_full_profile.png",
    ),
)


class StaleBlock(Exception):
    """docs/paper.md's block for a study differs from what its committed results give (one line)."""


def study_block(study: Study, *, scratch: Path) -> tuple[str, Path | None]:
    """The Markdown docs/paper.md shows for ``study`` (markers included), and the profile plot it drew."""
    store = ResultStore.read_only(study.results_dir)
    try:
        results = store.results()
    finally:
        store.close()
    section, plot_path = comparison_section(results, plots_dir=scratch / "plots")
    blocks = [_on_the_page(block, study=study) for block in section.blocks]
    body = render_markdown([Section("", blocks)], scratch).split("\n", 2)[2]  # drop the heading: the page has its own
    return f"{study.begin_marker}\n\n{body.rstrip()}\n\n{study.end_marker}", plot_path


def _on_the_page(block, *, study: Study):
    """The profile plot as the page links it (beside docs/paper.md), not where the report drew it."""
    if isinstance(block, Plot):
        caption = block.caption.replace("\n", " ")
        return f"![performance profile of {study.name}]({study.profile_png.name})\n\n*{caption}*"
    return block


def current_block(study: Study, page: str) -> str:
    """The block the page holds now for ``study``; :class:`StaleBlock` when its markers are missing."""
    start, end = page.find(study.begin_marker), page.find(study.end_marker)
    if start < 0 or end < start:
        raise StaleBlock(f"{PAPER}: no generated block for {study.name} (its markers are missing)")
    return page[start : end + len(study.end_marker)]


def check(study: Study, *, scratch: Path, page: str | None = None) -> None:
    """Raise :class:`StaleBlock` when the page's block for ``study`` (default: docs/paper.md's) is not what its
    results give."""
    expected, _ = study_block(study, scratch=scratch)
    page = PAPER.read_text(encoding="utf-8") if page is None else page
    if current_block(study, page) != expected:
        raise StaleBlock(
            f"{PAPER}: the block for {study.name} differs from what experiments/results/{study.name} gives "
            "(run `python -m orchestrator.report.studies --write`)"
        )


def write(study: Study, *, scratch: Path) -> None:
    """Replace docs/paper.md's block for ``study`` with what its results give, and copy the profile beside it."""
    block, plot_path = study_block(study, scratch=scratch)
    page = PAPER.read_text(encoding="utf-8")
    PAPER.write_text(page.replace(current_block(study, page), block), encoding="utf-8")
    if plot_path is not None:
        shutil.copyfile(plot_path, study.profile_png)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.report.studies", description=__doc__.split("\n")[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite docs/paper.md's generated blocks")
    mode.add_argument("--check", action="store_true", help="exit 1 when a generated block is stale")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        for study in STUDIES:
            try:
                (write if args.write else check)(study, scratch=Path(scratch) / study.name)
            except StaleBlock as error:
                print(f"error: {error}", file=sys.stderr)
                return 1
            print(f"{study.name}: {'written' if args.write else 'up to date'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
