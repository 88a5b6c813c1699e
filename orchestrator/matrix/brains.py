"""The brains of a matrix file (``brains:`` and ``shadows:``): names, weights resolved from the file's folder,
constructor options and unique labels, each mistake at its line."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from brains.registry import UnknownBrainError, bus_name, is_brain_file, require_brain, shipped_weights
from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.schema import BrainFields, items, text_at
from protocol.deploy.typed_yaml import Document
from protocol.deploy.typed_yaml import Path as At
from protocol.keys import check_name

_OPTION_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def read_brain_entries(document: Document, value: Any, path: At, *, base_dir: Path) -> list[tuple[BrainEntry, At]]:
    """(entry, where it was written) of each item of a ``brains`` or ``shadows`` value (typed by the schema)."""
    return [
        (_brain_entry(document, item, item_path, base_dir=base_dir), item_path)
        for item, item_path in items(value, path)
    ]


def _brain_entry(document: Document, item: str | BrainFields, path: At, *, base_dir: Path) -> BrainEntry:
    fields = BrainFields(name=item) if isinstance(item, str) else item
    name_path = path if isinstance(item, str) else (*path, "name")
    name = text_at(document, fields.name, name_path)
    if is_brain_file(name):  # a Behavior Metrics brain file, next to the matrix file unless absolute
        name = str((base_dir / Path(name).expanduser()).resolve())
    try:
        require_brain(name)
    except UnknownBrainError as error:
        raise document.error(name_path, str(error)) from None
    weights = None
    if isinstance(fields.weights, str):
        weights = _weights(document, fields.weights, (*path, "weights"), base_dir=base_dir)
    options = _options(document, fields.options, (*path, "options"))
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


def _options(document: Document, options: dict[str, Any], path: At) -> tuple[tuple[str, Any], ...]:
    for key, value in options.items():
        if key == "weights":
            raise document.error(
                (*path, key), "give weights as the entry's own `weights`, not as an option", at_key=True
            )
        if not _OPTION_KEY.fullmatch(key):
            raise document.error(
                (*path, key), f"option name {key!r} must be an identifier (letters, digits, '_')", at_key=True
            )
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError):
            raise document.error(
                (*path, key),
                f"option {key!r} must be a JSON value (text, number, boolean, list, mapping), got {value!r}",
            ) from None
    return tuple(options.items())


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
    first: dict[str, int] = {}
    for entry, path in entries:
        if entry.label in first:
            raise document.error(
                path,
                f"duplicate brain label {entry.label!r} (also on line {first[entry.label]}; "
                f"labels of brains and shadows must differ: give one a `label`)",
            )
        first[entry.label] = document.line(path)
