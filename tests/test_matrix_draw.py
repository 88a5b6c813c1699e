"""Held-out conditions drawn from a seed (a matrix part's ``draw``): the same seed draws the same conditions, every
brain meets each of them, and nothing a brain's training data drove is drawn or may be named."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from brains.neural.checkpoint import read_checkpoint, write_checkpoint
from orchestrator.matrix.load import MatrixError, parse_matrix

ROOT = Path(__file__).resolve().parent.parent
TINY = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"

HELDOUT = "draw: {count: 8, seed: SEED, circuits: [random, twisty, montreal], variations: {line: [red, white]}}"


def matrix_text(*, seed: int = 3, brains: str = "[explicit, constant]", draw: str = HELDOUT) -> str:
    draw = draw.replace("SEED", str(seed))
    return f"brains: {brains}\nparts:\n  paper: {{circuits: [simple]}}\n  heldout:\n    {draw}\n"


def drawn(matrix) -> list[tuple[str, str, str]]:
    return [(e.brain.label, e.circuit, e.variation) for e in matrix.episodes if e.part == "heldout"]


def trained_on(folder: Path, circuits: list[str]) -> Path:
    """The shipped tiny network's checkpoint, recording that its training data drove ``circuits``."""
    raw = read_checkpoint(TINY)
    raw["dataset"] = {**raw.get("dataset", {}), "circuits": circuits}
    path = folder / "trained.ckpt"
    write_checkpoint(raw, path)
    return path


def test_the_same_seed_draws_the_same_distinct_conditions_and_every_brain_meets_each():
    first, again, other = (parse_matrix(matrix_text(seed=seed)) for seed in (3, 3, 4))
    assert drawn(first) == drawn(again)
    assert drawn(first) != drawn(other)
    by_brain: dict[str, list[tuple[str, str]]] = {}
    for brain, circuit, world in drawn(first):
        by_brain.setdefault(brain, []).append((circuit, world))
    assert set(by_brain) == {"explicit", "constant"}
    assert by_brain["explicit"] == by_brain["constant"]  # paired
    conditions = by_brain["explicit"]
    assert len(conditions) == len(set(conditions)) == 8
    families = {circuit.split(":")[0] for circuit, _ in conditions}
    assert families <= {"random", "twisty", "montreal"} and len(families) >= 2
    assert {world for _, world in conditions} <= {"line=red", "line=white"}
    # The fixed cells stay as written beside the draw.
    assert [(e.brain.label, e.circuit) for e in first.episodes if e.part == "paper"] == [
        ("explicit", "simple"),
        ("constant", "simple"),
    ]


def test_a_family_draw_never_gives_a_circuit_the_training_drove(tmp_path):
    plain = [circuit for _, circuit, _ in drawn(parse_matrix(matrix_text(brains="[explicit]")))]
    generated = [circuit for circuit in plain if ":" in circuit]
    weights = trained_on(tmp_path, generated)
    brains = f"[explicit, {{name: deepest_lstm_tiny_pilotnet, weights: {weights}}}]"
    held_out = {circuit for _, circuit, _ in drawn(parse_matrix(matrix_text(brains=brains)))}
    assert generated and not held_out & set(generated)


def test_the_grandprix_family_draws_grandprix_circuits_the_training_never_drove(tmp_path):
    """A draw of ``circuits: [grandprix]`` gives loadable grandprix:SEED circuits, and holds out the ones a brain's
    training data drove, as the other families do."""
    from circuits import load_circuit

    draw = "draw: {count: 4, seed: SEED, circuits: [grandprix], variations: {line: [red]}}"
    plain = [circuit for _, circuit, _ in drawn(parse_matrix(matrix_text(brains="[explicit]", draw=draw)))]
    assert len(set(plain)) == 4 and all(circuit.startswith("grandprix:") for circuit in plain)
    assert all(load_circuit(circuit).length_m >= 600.0 for circuit in plain)
    weights = trained_on(tmp_path, plain)
    brains = f"[explicit, {{name: deepest_lstm_tiny_pilotnet, weights: {weights}}}]"
    held_out = {circuit for _, circuit, _ in drawn(parse_matrix(matrix_text(brains=brains, draw=draw)))}
    assert len(held_out) == 4 and not held_out & set(plain)


def test_a_named_circuit_the_training_drove_is_refused_naming_both(tmp_path):
    weights = trained_on(tmp_path, ["montreal", "random:5"])
    brains = f"[explicit, {{name: deepest_lstm_tiny_pilotnet, label: tiny, weights: {weights}}}]"
    with pytest.raises(MatrixError) as caught:
        parse_matrix(matrix_text(brains=brains), source="study.yaml")
    message = str(caught.value)
    assert message.startswith("study.yaml:5:") and "'montreal'" in message and "'tiny'" in message
    assert str(weights) in message and "\n" not in message


@pytest.mark.parametrize(
    ("draw", "expected"),
    [
        ("draw: {count: 5, circuits: [simple, montreal], variations: {line: [red]}}", "only 2"),
        ("draw: {count: 2, circuits: [simpel]}", "unknown circuit 'simpel'"),
        ("draw: {count: 0, circuits: [random]}", ">= 1"),
        ("draw: {count: 2, circuits: [random], variations: {lane: [red]}}", "unknown variation key 'lane'"),
        ("draw: {count: 2, circuits: [random]}\n    circuits: [simple]", "give draw or circuits, not both"),
    ],
)
def test_a_bad_draw_is_one_line_at_its_line(draw, expected):
    with pytest.raises(MatrixError) as caught:
        parse_matrix(matrix_text(draw=draw), source="m.yaml")
    assert expected in str(caught.value) and str(caught.value).startswith("m.yaml:")


def test_the_cli_refuses_an_overlapping_draw_before_anything_starts(tmp_path):
    weights = trained_on(tmp_path, ["montreal"])
    path = tmp_path / "study.yaml"
    brains = f"[{{name: deepest_lstm_tiny_pilotnet, label: tiny, weights: {weights}}}]"
    path.write_text(matrix_text(brains=brains))
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "matrix", str(path), "-o", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "held-out circuit 'montreal'" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()
