"""A matrix brain entry over many training runs: ``weights`` as a glob of checkpoints, one entry per training seed,
every run meeting exactly the same conditions (paired), the seed kept in the results."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from brains.neural.checkpoint import read_checkpoint, write_checkpoint
from orchestrator.matrix.load import MatrixError, load_matrix
from orchestrator.report.statistics import ONE_RUN

ROOT = Path(__file__).resolve().parent.parent
TINY = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"
PILOTNET_X3 = ROOT / "brains" / "weights" / "pilotnet_x3.ckpt"


def training_run(folder: Path, *, seed: int, source: Path = TINY) -> Path:
    """A checkpoint that records training seed ``seed`` (the shipped weights, relabelled: no training needed)."""
    raw = read_checkpoint(source)
    raw["training"] = {**raw.get("training", {}), "seed": seed}
    return write_to(raw, folder / f"seed-{seed}" / "model.ckpt")


def write_to(raw: dict, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_checkpoint(raw, path)


def write_matrix(folder: Path, brains: str, *, circuits: str = "[simple, many_curves]") -> Path:
    path = folder / "seeds.yaml"
    path.write_text(f"name: seeds\nbrains:\n{brains}\ncircuits: {circuits}\nlimits: {{laps: 1, max_sim_seconds: 2}}\n")
    return path


def test_a_weights_glob_gives_one_entry_per_training_seed_on_the_same_conditions(tmp_path):
    for seed in (4, 0, 2):
        training_run(tmp_path / "runs", seed=seed)
    matrix = load_matrix(
        write_matrix(
            tmp_path,
            "  - explicit\n  - {name: deepest_lstm_tiny_pilotnet, label: tiny, weights: runs/seed-*/model.ckpt}\n",
        )
    )
    runs = [brain for brain in matrix.brains if brain.group == "tiny"]
    assert [(b.label, b.training_seed) for b in runs] == [("tiny-s0", 0), ("tiny-s2", 2), ("tiny-s4", 4)]
    assert all(
        b.compared_as == "tiny" and b.weights == tmp_path / "runs" / f"seed-{b.training_seed}" / "model.ckpt"
        for b in runs
    )
    assert matrix.brains[0].compared_as == "explicit" and matrix.brains[0].training_seed is None
    # Paired: every run of every brain meets exactly the same conditions, with the same episode seeds.
    conditions = {}
    for episode in matrix.episodes:
        conditions.setdefault(episode.brain.label, []).append(
            (episode.circuit, episode.variation, episode.perturbation, episode.spec.seed)
        )
    assert len(conditions) == 4 and len({tuple(c) for c in conditions.values()}) == 1
    assert runs[1].to_dict()["training_seed"] == 2 and "training_seed" not in matrix.brains[0].to_dict()


@pytest.mark.parametrize(
    ("make", "weights", "message"),
    [
        (lambda runs: None, "runs/seed-*/model.ckpt", "matches no file"),
        (
            lambda runs: (training_run(runs, seed=0), training_run(runs, seed=1, source=PILOTNET_X3)),
            "runs/seed-*/model.ckpt",
            "mixes networks",
        ),
        (
            lambda runs: (
                training_run(runs, seed=3),
                write_to(read_checkpoint(runs / "seed-3" / "model.ckpt"), runs / "copy" / "model.ckpt"),
            ),
            "runs/*/model.ckpt",
            "both training seed 3",
        ),
    ],
    ids=["no-match", "two-networks", "same-seed"],
)
def test_a_bad_weights_glob_is_one_line_at_its_line(tmp_path, make, weights, message):
    make(tmp_path / "runs")
    path = write_matrix(tmp_path, f"  - explicit\n  - {{name: neural, label: tiny, weights: '{weights}'}}\n")
    with pytest.raises(MatrixError, match=message) as error:
        load_matrix(path)
    assert str(error.value).startswith(f"{path}:4:") and "\n" not in str(error.value)


def test_a_named_network_refuses_a_glob_of_another_network(tmp_path):
    training_run(tmp_path / "runs", seed=0, source=PILOTNET_X3)
    path = write_matrix(tmp_path, "  - {name: deepest_lstm_tiny_pilotnet, weights: runs/*/model.ckpt}\n")
    with pytest.raises(MatrixError, match="serves deepest_lstm_tiny_pilotnet checkpoints"):
        load_matrix(path)


@pytest.mark.integration
def test_results_keep_the_training_seed_as_a_column(tmp_path):
    for seed in (0, 1):
        training_run(tmp_path / "runs", seed=seed)
    path = write_matrix(
        tmp_path,
        "  - explicit\n  - {name: deepest_lstm_tiny_pilotnet, label: tiny, weights: runs/seed-*/model.ckpt}\n",
        circuits="[simple]",
    )
    run_matrix(path, out=tmp_path / "out")
    with open(tmp_path / "out" / "episodes.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    assert [(r["brain"], r["brain_group"], r["training_seed"], r["status"]) for r in rows] == [
        ("explicit", "explicit", "", "done"),
        ("tiny-s0", "tiny", "0", "done"),
        ("tiny-s1", "tiny", "1", "done"),
    ]
    # The report compares brains with intervals over training runs, and says where there is one run only.
    report = (tmp_path / "out" / "report.md").read_text()
    comparison = report.split("## Comparison with intervals", 1)[1].split("\n## ", 1)[0]
    assert "| tiny | 2 (seeds 0, 1) | 1 |" in comparison, comparison
    assert "| explicit | 1 (one training run) | 1 |" in comparison and "one training run: no interval" in comparison
    assert "P(X > Y)" in comparison and (tmp_path / "out" / "plots" / "performance_profile.png").is_file()


@pytest.mark.slow  # nine episodes: about a minute under load
def test_a_matrix_with_parts_gets_each_brains_interval_per_part(tmp_path):
    """A study's parts are its question's axes (the flat and the gazebo look, say): the comparison gives each brain's
    figures per part too, over that part's own conditions."""
    for seed in (0, 1):
        training_run(tmp_path / "runs", seed=seed)
    path = tmp_path / "parts.yaml"
    path.write_text(
        "name: parts\nbrains:\n  - explicit\n  - {name: deepest_lstm_tiny_pilotnet, label: tiny, weights: "
        "runs/seed-*/model.ckpt}\nlimits: {laps: 1, max_sim_seconds: 2}\nparts:\n  red:\n    circuits: [simple]\n"
        "  white:\n    circuits: [simple]\n    worlds: [{line: white}]\n    repetitions: 2\n"
    )
    run_matrix(path, out=tmp_path / "out")
    report = (tmp_path / "out" / "report.md").read_text()
    comparison = report.split("## Comparison with intervals", 1)[1].split("\n## ", 1)[0]
    assert "| Part | Brain | Conditions |" in comparison, comparison
    for part, conditions in (("red", 1), ("white", 2)):
        assert f"| {part} | tiny | {conditions} |" in comparison, comparison
        assert f"| {part} | explicit | {conditions} |" in comparison and ONE_RUN in comparison, comparison


def run_matrix(path: Path, *, out: Path) -> None:
    """``drivebench matrix PATH -o OUT`` as a user runs it, which must succeed."""
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "matrix", str(path), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
