"""Held-out conditions drawn from a seed: a matrix part's ``draw`` (issue 28).

A fixed list of cells tests what its author thought of; a draw tests conditions nobody chose. A part::

    heldout:
      draw:
        count: 20                   # distinct (circuit, world) conditions
        seed: 7                     # the same seed draws the same conditions
        circuits: [random, twisty, grandprix, montreal]   # generator families and/or named circuits
        variations: {line: [red, white, none], road: [grey, white]}   # each condition draws one value per key

Each condition picks one entry of ``circuits`` uniformly; a family (``random``, ``twisty``, ``grandprix``) becomes
a circuit of that family with a drawn seed, a name stays itself. Then one value of each variation key. Every brain
meets every drawn condition (paired), under each perturbation and repetition of the part.

Held out means held out: a circuit that a brain's checkpoint lists among the circuits its training data drove
(``dataset.circuits``, written by ``drivebench train``) is refused when named, and never drawn from a family.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orchestrator.matrix.conditions import Axis, World, read_axes, read_world
from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.schema import Draw, items, text_at
from protocol.deploy.typed_yaml import Document
from protocol.deploy.typed_yaml import Path as At

FAMILIES = ("random", "twisty", "grandprix")  # circuits generated from a seed (circuits.library)
_FAMILY_SEEDS = (1000, 100_000)  # drawn generator seeds; the shipped recipes train on seeds below 1000
_TRIES_PER_CONDITION = 50


@dataclass(frozen=True)
class DrawnConditions:
    """The conditions a draw gave, in drawn order, and the axes their worlds vary on."""

    conditions: tuple[tuple[str, World], ...]
    axes: tuple[Axis, ...]

    @property
    def circuits(self) -> list[str]:
        return list(dict.fromkeys(circuit for circuit, _ in self.conditions))

    @property
    def worlds(self) -> list[World]:
        return list({world.label: world for _, world in self.conditions}.values())


def draw_conditions(
    document: Document, draw: Draw, path: At, *, brains: tuple[BrainEntry, ...], check_circuit
) -> DrawnConditions | None:
    """Draw ``draw.count`` distinct conditions; ``check_circuit(document, value, path)`` reads a circuit name.
    Notes each mistake in the circuits (an overlap with training data among them) and the variations, and then
    returns None; raises the document's error (one line, at the key) when they give too few conditions."""
    trained = _training_circuits(brains)
    before = document.noted
    entries = _circuit_entries(document, draw, (*path, "circuits"), trained=trained, check_circuit=check_circuit)
    axes = read_axes(document, draw.variations, (*path, "variations"))
    if document.noted > before:
        return None  # "too few conditions" would follow from what was left out
    rng = random.Random(draw.seed)
    drawn: dict[tuple[str, str], tuple[str, World]] = {}
    for _ in range(draw.count * _TRIES_PER_CONDITION):
        if len(drawn) == draw.count:
            break
        circuit = _draw_circuit(rng, rng.choice(entries), trained=trained)
        world = read_world([(axis.key, rng.choice(axis.values)[1]) for axis in axes])
        drawn.setdefault((circuit, world.label), (circuit, world))
    if len(drawn) < draw.count:
        raise document.error(
            (*path, "count"),
            f"draw asks for {draw.count} distinct conditions; its circuits and variations give only {len(drawn)}",
        )
    return DrawnConditions(conditions=tuple(drawn.values()), axes=tuple(axes))


def _circuit_entries(document: Document, draw: Draw, path: At, *, trained: dict[str, str], check_circuit) -> list[str]:
    """The draw's circuit entries; one with a mistake is noted and left out."""
    entries = []
    for value, item_path in items(draw.circuits, path):
        text = document.attempt(
            _circuit_entry, document, value, item_path, trained=trained, check_circuit=check_circuit
        )
        if text is not None:
            entries.append(text)
    return entries


def _circuit_entry(document: Document, value: Any, path: At, *, trained: dict[str, str], check_circuit) -> str:
    text = text_at(document, value, path)
    if text in FAMILIES:
        return text
    text = check_circuit(document, text, path)
    if text in trained:
        raise document.error(
            path,
            f"held-out circuit {text!r} is in the training data of {trained[text]} (draw circuits the training "
            "never drove)",
        )
    return text


def _draw_circuit(rng: random.Random, entry: str, *, trained: dict[str, str]) -> str:
    if entry not in FAMILIES:
        return entry
    while True:
        name = f"{entry}:{rng.randrange(*_FAMILY_SEEDS)}"
        if name not in trained:
            return name


def _training_circuits(brains: tuple[BrainEntry, ...]) -> dict[str, str]:
    """Circuit -> "brain LABEL (CHECKPOINT)" for every circuit a brain's checkpoint says its training drove."""
    trained: dict[str, str] = {}
    for brain in brains:
        for circuit in _checkpoint_circuits(brain.weights):
            trained.setdefault(circuit, f"brain {brain.label!r} ({brain.weights})")
    return trained


def _checkpoint_circuits(weights: Path | None) -> list[str]:
    if weights is None or weights.suffix.lower() != ".ckpt" or not weights.is_file():
        return []
    from brains.neural.checkpoint import CheckpointError, read_checkpoint  # torch: only when a draw meets a network

    try:
        dataset: Any = read_checkpoint(weights).get("dataset", {})
    except CheckpointError:
        return []  # serving it reports the problem, at its line
    circuits = dataset.get("circuits", []) if isinstance(dataset, dict) else []
    return [str(circuit) for circuit in circuits]
