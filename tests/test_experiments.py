"""Every matrix file that ships in experiments/ plans: its brains' weights exist (a study names its training runs
with a glob, and a folder renamed or a seed folder lost would only show when someone drives it), its draws draw, its
schema holds. Planning loads no network and starts no process."""

from __future__ import annotations

from pathlib import Path

import pytest

from orchestrator.cli import main

EXPERIMENTS = sorted((Path(__file__).resolve().parent.parent / "experiments").glob("*.yaml"))


def test_the_experiments_folder_holds_the_studies():
    assert {"paper.yaml", "memory_study.yaml", "randomised_full.yaml"} <= {path.name for path in EXPERIMENTS}


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[path.name for path in EXPERIMENTS])
def test_every_shipped_matrix_file_plans(path, capsys):
    assert main(["matrix", str(path), "--plan"]) == 0, capsys.readouterr().err
    assert " seed " in capsys.readouterr().out  # one planned episode a line
