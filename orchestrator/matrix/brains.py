"""The brains of a matrix file (``brains:`` and ``shadows:``): names, weights resolved from the file's folder,
constructor options and unique labels, each mistake at its line.

``weights`` may be a glob (``runs/train/tiny-s*/model.ckpt``): one entry per checkpoint, each a training run of
the same brain. The entries share the written label as their ``group`` (what reports compare) and are labelled
``<group>-s<training seed>``, the seed read from the checkpoint itself."""

from __future__ import annotations

import glob
import json
import re
from pathlib import Path
from typing import Any

from brains.registry import UnknownBrainError, bus_name, is_brain_file, require_brain, shipped_network, shipped_weights
from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.schema import BrainFields, items, text_at
from protocol.deploy.typed_yaml import Document
from protocol.deploy.typed_yaml import Path as At
from protocol.keys import check_name

_OPTION_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


GLOB_CHARACTERS = frozenset("*?[")


def read_brain_entries(document: Document, value: Any, path: At, *, base_dir: Path) -> list[tuple[BrainEntry, At]]:
    """(entry, where it was written) of each item of a ``brains`` or ``shadows`` value (typed by the schema); an
    item whose weights are a glob gives one entry per matching checkpoint. An item with a mistake is noted and left
    out."""
    entries = []
    for item, item_path in items(value, path):
        if isinstance(item, BrainFields) and isinstance(item.weights, str) and GLOB_CHARACTERS & set(item.weights):
            runs = document.attempt(_training_runs, document, item, item_path, base_dir=base_dir) or []
            entries += [(entry, item_path) for entry in runs]
        elif (entry := document.attempt(_brain_entry, document, item, item_path, base_dir=base_dir)) is not None:
            entries.append((entry, item_path))
    return entries


def _training_runs(document: Document, fields: BrainFields, path: At, *, base_dir: Path) -> list[BrainEntry]:
    """One entry per checkpoint the weights glob matches, labelled by its training seed."""
    name = _brain_name(document, fields.name, (*path, "name"), base_dir=base_dir)
    where = (*path, "weights")
    pattern = text_at(document, str(fields.weights), where)
    full = str(Path(pattern).expanduser() if Path(pattern).expanduser().is_absolute() else base_dir / pattern)
    paths = sorted(Path(found).resolve() for found in glob.glob(full, recursive=True))
    if not paths:
        raise document.error(where, f"weights pattern {pattern!r} matches no file (looked for {full})")
    options = _options(document, fields.options, (*path, "options"))
    if options is None:  # noted
        return []
    group = _label(document, fields.label if isinstance(fields.label, str) else None, path, name=name, weights=None)
    seeds: dict[int, Path] = {}
    network = ""
    entries = []
    for weights in paths:
        model, seed = _network_and_seed(document, where, weights)
        if network and model != network:
            raise document.error(
                where,
                f"weights pattern {pattern!r} mixes networks: {paths[0]} holds {network}, {weights} holds {model}",
            )
        if seed in seeds:
            raise document.error(
                where,
                f"weights pattern {pattern!r}: {seeds[seed]} and {weights} are both training "
                f"seed {seed} (one checkpoint per training run)",
            )
        network, seeds[seed] = model, weights
        label = _label(document, f"{group}-s{seed}", path, name=name, weights=None)
        entries.append(
            BrainEntry(label=label, brain=name, weights=weights, options=options, group=group, training_seed=seed)
        )
    if (expected := shipped_network(name)) is not None and network != expected:
        raise document.error(where, f"brain {name!r} serves {expected} checkpoints; {pattern!r} matches {network}")
    return entries


def _network_and_seed(document: Document, where: At, weights: Path) -> tuple[str, int]:
    """The network a checkpoint holds and the training seed it records (torch loads here, as it would to serve)."""
    from brains.neural.checkpoint import CheckpointError, load_checkpoint

    if weights.suffix.lower() != ".ckpt":
        raise document.error(
            where, f"{weights}: a weights pattern takes checkpoints (.ckpt), which record their training seed"
        )
    try:
        checkpoint = load_checkpoint(weights)
    except CheckpointError as error:
        raise document.error(where, str(error)) from None
    seed = checkpoint.training.get("seed")
    if not isinstance(seed, int):
        raise document.error(where, f"{weights} records no training seed (not written by drivebench train?)")
    return checkpoint.model, seed


def _brain_name(document: Document, written: str, where: At, *, base_dir: Path) -> str:
    name = text_at(document, written, where)
    if is_brain_file(name):  # a Behavior Metrics brain file, next to the matrix file unless absolute
        name = str((base_dir / Path(name).expanduser()).resolve())
    try:
        require_brain(name)
    except UnknownBrainError as error:
        raise document.error(where, str(error)) from None
    return name


def _brain_entry(document: Document, item: str | BrainFields, path: At, *, base_dir: Path) -> BrainEntry | None:
    """The entry written at ``path``, or None once its mistakes are noted: its name, weights and options are each
    checked, a mistake in one says nothing of the others."""
    fields = BrainFields(name=item) if isinstance(item, str) else item
    before = document.noted
    where = path if isinstance(item, str) else (*path, "name")
    name = document.attempt(_brain_name, document, fields.name, where, base_dir=base_dir)
    weights = None
    if isinstance(fields.weights, str):
        weights = document.attempt(_weights, document, fields.weights, (*path, "weights"), base_dir=base_dir)
    options = _options(document, fields.options, (*path, "options"))
    if name is None or options is None or document.noted > before:
        return None
    label = _label(document, fields.label if isinstance(fields.label, str) else None, path, name=name, weights=weights)
    # A network named without weights serves its shipped checkpoint: say which, for the reports (tables 1 and 2).
    return BrainEntry(label=label, brain=name, weights=weights or shipped_weights(name), options=options)


def _weights(document: Document, written: str, path: At, *, base_dir: Path) -> Path:
    written = text_at(document, written, path)
    weights = base_dir / written
    try:
        weights = Path(written).expanduser()
        weights = (weights if weights.is_absolute() else base_dir / weights).resolve()
        found = weights.exists()
    except (OSError, ValueError, RuntimeError):  # a NUL byte, an unknown ~user, a symlink loop
        found = False
    if not found:
        raise document.error(
            path,
            f"weights file {written!r} not found (looked for {weights}; relative paths start at the matrix file's "
            "folder)",
        )
    return weights


def _options(document: Document, options: dict[str, Any], path: At) -> tuple[tuple[str, Any], ...] | None:
    """The options in written order, or None once the mistake of each option that has one is noted."""
    before = document.noted
    for key, value in options.items():
        document.attempt(_check_option, document, key, value, (*path, key))
    return tuple(options.items()) if document.noted == before else None


def _check_option(document: Document, key: str, value: Any, path: At) -> None:
    if key == "weights":
        raise document.error(path, "give weights as the entry's own `weights`, not as an option", at_key=True)
    if not _OPTION_KEY.fullmatch(key):
        raise document.error(path, f"option name {key!r} must be an identifier (letters, digits, '_')", at_key=True)
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError):
        raise document.error(
            path, f"option {key!r} must be a JSON value (text, number, boolean, list, mapping), got {value!r}"
        ) from None


def _label(document: Document, written: str | None, path: At, *, name: str, weights: Path | None) -> str:
    if written is not None:
        label = text_at(document, written, (*path, "label"))
        where = (*path, "label")
    else:
        # "-" and not "@": the label is the brain's bus name, and key chunks allow letters, digits, _ . - only.
        label = bus_name(name) if weights is None else f"{bus_name(name)}-{weights.stem}"
        where = path
    try:
        return check_name(label, what="brain label")
    except ValueError as error:
        hint = "" if written is not None else "; give the entry a `label`"
        raise document.error(where, f"{error} (it is the brain's bus name{hint})") from None


def check_unique_labels(document: Document, entries: list[tuple[BrainEntry, At]]) -> None:
    """Note each entry whose label an earlier entry has."""
    first: dict[str, int] = {}
    for entry, path in entries:
        if entry.label in first:
            document.note(
                document.error(
                    path,
                    f"duplicate brain label {entry.label!r} (also on line {first[entry.label]}; "
                    f"labels of brains and shadows must differ: give one a `label`)",
                )
            )
            continue
        first[entry.label] = document.line(path)
