"""``drivebench paper``: the paper's tables, ours beside its figures (``orchestrator.report.paper`` writes them)."""

from __future__ import annotations

import argparse
from pathlib import Path

from orchestrator.cli.errors import UsageError
from orchestrator.cli.matrix import add_run_options, load_matrix_file, run_matrix_args
from orchestrator.report.matrix import PAPER_FACT
from orchestrator.report.paper import (
    PAPER_FILE,
    PARTS,
    SMOKE_BRAINS,
    SMOKE_CELLS_PER_PART,
    SMOKE_SIM_SECONDS,
    smoke_matrix,
)


def add(commands: argparse._SubParsersAction) -> None:
    paper = commands.add_parser(
        "paper",
        help="regenerate the paper's six tables (ours beside the paper's figures)",
        description="Run experiments/paper.yaml (every brain, circuit, world and perturbation the paper's closed-loop "
        "tables need) as a matrix, then write DIR/report.html, report.md and paper.md with the paper's "
        "figure beside ours in every cell. Add your own brain to the file to get its row.",
    )
    paper.add_argument(
        "--file", type=Path, default=PAPER_FILE, help="the paper's matrix file (default: experiments/paper.yaml)"
    )
    add_run_options(paper, default_out="runs/paper-<time>", default_workers=2)
    paper.add_argument(
        "--smoke",
        action="store_true",
        help=f"a seconds-long form: {' and '.join(SMOKE_BRAINS)} (a study's file: the first two training runs of "
        f"each brain), the first {SMOKE_CELLS_PER_PART} cells of every table, {SMOKE_SIM_SECONDS:g} s each "
        "(what CI runs)",
    )
    paper.set_defaults(func=run_paper_command)


def run_paper_command(args: argparse.Namespace) -> int:
    matrix = load_matrix_file(args.file)
    if not set(PARTS) & set(matrix.parts):
        raise UsageError(f"{args.file}: no part named {', '.join(PARTS)}: not a paper matrix")
    if args.smoke:
        matrix = smoke_matrix(matrix)
        if not matrix.episodes:
            raise UsageError(f"{args.file}: --smoke needs the brains {', '.join(SMOKE_BRAINS)}")
    command = (
        "drivebench paper"
        + (f" --file {args.file}" if args.file != PAPER_FILE else "")
        + (" --smoke" if args.smoke else "")
    )
    return run_matrix_args(
        matrix, args, what="paper", default_folder=matrix.name, command=command, facts={PAPER_FACT: True}
    )
