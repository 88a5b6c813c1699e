"""Reading a YAML file node by node, so that every mistake names its line: ``FILE:LINE: what is wrong``.

:class:`NodeReader` turns nodes into values and raises the caller's error type (a :class:`FileError`) at the
node's line; duplicate keys, unknown keys, empty lists and unreadable tags are all caught here.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

import yaml
from yaml.constructor import SafeConstructor


class FileError(ValueError):
    """A mistake in a file. ``str(error)`` is one line: ``FILE:LINE: what is wrong (what is allowed)``
    (``FILE: ...`` when the file itself cannot be read). ``source``, ``line`` (1-based, or None) and ``message``
    are kept as attributes."""

    def __init__(self, message: str, *, source: str, line: int | None) -> None:
        self.message = re.sub(r"\s*\n\s*", " ", message).strip()
        self.source = source
        self.line = line
        where = source if line is None else f"{source}:{line}"
        super().__init__(f"{where}: {self.message}")


def line_of(node: yaml.Node) -> int:
    return node.start_mark.line + 1


class NodeReader:
    """Turns YAML nodes into values, raising ``error_type`` at the node's line. ``top_level_keys`` are named when
    the file is not a mapping."""

    def __init__(
        self, source: str, *, error_type: type[FileError] = FileError, top_level_keys: Iterable[str] = ()
    ) -> None:
        self.source = source
        self.error_type = error_type
        self.top_level_keys = tuple(top_level_keys)

    def error(self, node: yaml.Node | None, message: str) -> FileError:
        return self.error_type(message, source=self.source, line=1 if node is None else line_of(node))

    def compose(self, text: str) -> yaml.Node:
        try:
            root = yaml.compose(text, Loader=yaml.SafeLoader)
        except yaml.MarkedYAMLError as error:
            mark = error.problem_mark or error.context_mark
            line = 1 if mark is None else mark.line + 1
            raise self.error_type(
                f"invalid YAML: {error.problem or error.context}", source=self.source, line=line
            ) from None
        except yaml.YAMLError as error:  # a character YAML does not allow: a position, no mark
            position = getattr(error, "position", None)
            line = 1 if position is None else text.count("\n", 0, position) + 1
            raise self.error_type(f"invalid YAML: {error}", source=self.source, line=line) from None
        if not isinstance(root, yaml.MappingNode):
            raise self.error_type(
                "the top level must be a mapping (keys: " + ", ".join(self.top_level_keys) + ")",
                source=self.source,
                line=1 if root is None else line_of(root),
            )
        self._check_duplicates(root, seen=set())
        return root

    def _check_duplicates(self, node: yaml.Node, *, seen: set[int]) -> None:
        if id(node) in seen:  # aliases may make cycles
            return
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, int] = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else id(key_node)
                if key in first:
                    raise self.error(key_node, f"duplicate key {key!r} (first on line {first[key]})")
                first[key] = line_of(key_node)
                self._check_duplicates(value_node, seen=seen)
        elif isinstance(node, yaml.SequenceNode):
            for item in node.value:
                self._check_duplicates(item, seen=seen)

    def mapping(
        self, node: yaml.Node, *, what: str, allowed: Iterable[str] | None = None
    ) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """key -> (key node, value node), in written order; keys must be text (and within ``allowed``)."""
        if not isinstance(node, yaml.MappingNode):
            raise self.error(node, f"{what} must be a mapping, got {describe(node)}")
        allowed = None if allowed is None else tuple(allowed)
        entries = {}
        for key_node, value_node in node.value:
            key = self.value(key_node)
            if not isinstance(key, str):
                raise self.error(key_node, f"keys of {what} must be text, got {key!r}")
            if allowed is not None and key not in allowed:
                raise self.error(key_node, f"unknown key {key!r} in {what} (allowed: {', '.join(allowed)})")
            entries[key] = (key_node, value_node)
        return entries

    def items(self, node: yaml.Node, *, what: str) -> list[yaml.Node]:
        """The items of a non-empty list; any other node stands for a one-item list."""
        if isinstance(node, yaml.SequenceNode):
            if not node.value:
                raise self.error(node, f"{what} is an empty list (give at least one)")
            return list(node.value)
        if isinstance(node, yaml.ScalarNode) and self.value(node) is None:
            raise self.error(node, f"{what} is empty (give at least one)")
        return [node]

    def value(self, node: yaml.Node) -> Any:
        """The plain Python value of a node (YAML 1.1 rules: ``on``/``off`` are booleans)."""
        try:
            return SafeConstructor().construct_object(node, deep=True)
        except yaml.YAMLError as error:  # a tag the safe loader does not know (!!python/object, !custom)
            problem = getattr(error, "problem", None) or error
            raise self.error(node, f"cannot read this value: {problem}") from None

    def scalar(self, node: yaml.Node, *, what: str) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            raise self.error(node, f"{what} must be a single value, got {describe(node)}")
        return self.value(node)

    def text(self, node: yaml.Node, *, what: str) -> str:
        value = self.scalar(node, what=what)
        if not isinstance(value, str) or not value.strip():
            raise self.error(node, f"{what} must be text, got {value!r}")
        return value.strip()

    def integer(self, node: yaml.Node, *, what: str, minimum: int) -> int:
        value = self.scalar(node, what=what)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise self.error(node, f"{what} must be an integer >= {minimum}, got {value!r}")
        return value

    def yaml_text(self, node: yaml.Node, text: str) -> Any:
        """A value written inside a string (``"gaussian=10"``), read as YAML like the command line does."""
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError:
            raise self.error(node, f"cannot read the value {text.strip()!r}") from None


def describe(node: yaml.Node) -> str:
    if node.tag == "tag:yaml.org,2002:null":
        return "nothing"
    if isinstance(node, yaml.MappingNode):
        return "a mapping"
    if isinstance(node, yaml.SequenceNode):
        return "a list"
    return repr(node.value)


def label_text(value: Any) -> str:
    """A value as it appears in labels: booleans as on/off, floats in their shortest exact form."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return repr(value)
    if value is None:
        return "none"
    return str(value)
