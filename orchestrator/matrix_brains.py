"""The brains of a matrix file (``brains:`` and ``shadows:``): names, weights resolved from the file's folder,
constructor options and unique labels, each mistake at its line."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import yaml

from brains.registry import UnknownBrainError, bus_name, is_brain_file, require_brain
from orchestrator.matrix_plan import (
    BrainEntry,
)
from orchestrator.yaml_nodes import NodeReader, line_of
from protocol.keys import check_name

# The protocol's own lists of world and camera variation keys (it has no public name for them).

BRAIN_KEYS = ("name", "weights", "label", "options")
_OPTION_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


# -- brains ------------------------------------------------------------------------------------------------------


def read_brain_entries(
    reader: NodeReader, node: yaml.Node, *, what: str, base_dir: Path
) -> list[tuple[BrainEntry, yaml.Node]]:
    return [(_brain_entry(reader, item, what=what, base_dir=base_dir), item) for item in reader.items(node, what=what)]


def _brain_entry(reader: NodeReader, node: yaml.Node, *, what: str, base_dir: Path) -> BrainEntry:
    if isinstance(node, yaml.MappingNode):
        fields = reader.mapping(node, what=f"a {what} entry", allowed=BRAIN_KEYS)
    else:
        fields = {"name": (node, node)}
    if "name" not in fields:
        raise reader.error(node, f"a {what} entry needs a name (keys: {', '.join(BRAIN_KEYS)})")
    name_node = fields["name"][1]
    name = reader.text(name_node, what="a brain name")
    if is_brain_file(name):  # a Behavior Metrics brain file, next to the matrix file unless absolute
        name = str((base_dir / Path(name).expanduser()).resolve())
    try:
        require_brain(name)
    except UnknownBrainError as error:
        raise reader.error(name_node, str(error)) from None
    weights = _weights(reader, fields["weights"][1], base_dir=base_dir) if "weights" in fields else None
    options = _options(reader, fields["options"][1]) if "options" in fields else ()
    label = _label(reader, fields.get("label", (node, None))[1], name=name, weights=weights, entry=node)
    return BrainEntry(label=label, brain=name, weights=weights, options=options)


def _weights(reader: NodeReader, node: yaml.Node, *, base_dir: Path) -> Path:
    written = reader.text(node, what="weights")
    path = base_dir / written
    try:
        path = Path(written).expanduser()
        path = (path if path.is_absolute() else base_dir / path).resolve()
        found = path.exists()
    except (OSError, ValueError, RuntimeError):  # a NUL byte, an unknown ~user, a symlink loop
        found = False
    if not found:
        raise reader.error(
            node,
            f"weights file {written!r} not found (looked for {path}; relative paths start at the matrix file's folder)",
        )
    return path


def _options(reader: NodeReader, node: yaml.Node) -> tuple[tuple[str, Any], ...]:
    options = []
    for key, (key_node, value_node) in reader.mapping(node, what="options").items():
        if key == "weights":
            raise reader.error(key_node, "give weights as the entry's own `weights`, not as an option")
        if not _OPTION_KEY.fullmatch(key):
            raise reader.error(key_node, f"option name {key!r} must be an identifier (letters, digits, '_')")
        value = reader.value(value_node)
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError):
            raise reader.error(
                value_node, f"option {key!r} must be a JSON value (text, number, boolean, list, mapping), got {value!r}"
            ) from None
        options.append((key, value))
    return tuple(options)


def _label(reader: NodeReader, node: yaml.Node | None, *, name: str, weights: Path | None, entry: yaml.Node) -> str:
    if node is not None:
        label = reader.text(node, what="label")
        where = node
    else:
        # "-" and not "@": the label is the brain's bus name, and key chunks allow letters, digits, _ . - only.
        label = bus_name(name) if weights is None else f"{bus_name(name)}-{weights.stem}"
        where = entry
    try:
        return check_name(label, what="brain label")
    except ValueError as error:
        hint = "" if node is not None else "; give the entry a `label`"
        raise reader.error(where, f"{error} (it is the brain's bus name{hint})") from None


def check_unique_labels(reader: NodeReader, entries: list[tuple[BrainEntry, yaml.Node]]) -> None:
    first: dict[str, int] = {}
    for entry, node in entries:
        if entry.label in first:
            raise reader.error(
                node,
                f"duplicate brain label {entry.label!r} (also on line {first[entry.label]}; "
                f"labels of brains and shadows must differ: give one a `label`)",
            )
        first[entry.label] = line_of(node)
