"""``drivebench report DIR``: tables and plots of a matrix's results (``orchestrator.report.matrix`` writes them)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orchestrator.cli.errors import EXIT_OK, UsageError


def add(commands: argparse._SubParsersAction) -> None:
    """``drivebench report DIR [-o FOLDER]``."""
    parser = commands.add_parser(
        "report",
        help="tables and plots of a matrix's results (HTML, Markdown, CSV)",
        description="Read DIR/results.sqlite (written by `drivebench matrix`) and write report.html (self-contained), "
        "report.md, episodes.csv and plots/*.png: the paper's main table per brain and circuit, "
        "generalisation and robustness grids, internal metrics, failures, trajectories on the circuit.",
    )
    parser.add_argument("dir", type=Path, metavar="DIR", help="the matrix's output folder")
    parser.add_argument("-o", "--output", type=Path, metavar="FOLDER", help="write the report here instead of into DIR")
    parser.set_defaults(func=run_report)


def run_report(args: argparse.Namespace) -> int:
    """Run ``drivebench report``: 0 with the written paths on stderr; 2 with one error line on stderr."""
    from orchestrator.matrix.results import ResultsError
    from orchestrator.report.data import ReportError
    from orchestrator.report.matrix import write_report

    try:
        files = write_report(args.dir, output=getattr(args, "output", None))
    except (ReportError, ResultsError) as error:
        raise UsageError(str(error)) from None
    written = [files.html, files.markdown, files.csv, *([files.parquet] if files.parquet else [])]
    for path in written:
        print(f"wrote {path}", file=sys.stderr)
    if files.plots:
        print(f"wrote {len(files.plots)} plot(s) in {files.plots[0].parent}", file=sys.stderr)
    return EXIT_OK
