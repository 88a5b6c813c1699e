"""YAML files read into msgspec types, every mistake one line: ``FILE:LINE: what is wrong``.

:func:`compose` reads the text into plain data and remembers the line of every value and key by its path
(``("limits", "laps")``, ``("brains", 1, "weights")``); duplicate keys, unreadable tags and invalid YAML fail there.
:func:`convert` turns the data into a type (``msgspec.Struct`` with ``forbid_unknown_fields=True`` and
``Annotated[..., msgspec.Meta(...)]`` constraints) and rewords msgspec's ``... - at `$.x.y``` into that line:
``m.yaml:4: limits.laps must be an integer >= 1, got 0``. :func:`explain` gives the path and message alone, for
callers that decide the source themselves (a config's command-line overrides). A reader that checks more than
the types (a matrix's circuits, brains, values) notes each mistake on the document (:meth:`Document.attempt`) and
goes on, so that one error reports them all. No Zenoh here.
"""

from __future__ import annotations

import re
import types
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, ParamSpec, TypeVar, Union, get_args, get_origin

import msgspec
import yaml
from yaml.constructor import SafeConstructor

from protocol.episode_spec import bound_text
from protocol.suggest import did_you_mean

T = TypeVar("T")
P = ParamSpec("P")
Path = tuple[Hashable, ...]  # keys of mappings and indexes of lists, from the top

_MAP_TAG = "tag:yaml.org,2002:map"
_SEQ_TAG = "tag:yaml.org,2002:seq"
_MERGE_TAG = "tag:yaml.org,2002:merge"
# msgspec's names for what it expected or got, as a sentence says them.
_TYPE_WORDS = {
    "int": "an integer",
    "float": "a number",
    "str": "text",
    "bool": "true or false",
    "object": "a mapping",
    "array": "a list",
    "null": "nothing",
}
_AT = re.compile(r" - at `(?:key` in `)?(\$[^`]*)`$")
_SEGMENT = re.compile(r"\.([^.\[]+)|\[(\d+|\.\.\.)\]")


class FileError(ValueError):
    """A mistake in a file. ``str(error)`` is one line: ``FILE:LINE: what is wrong (what is allowed)``
    (``FILE: ...`` when the file itself cannot be read). ``source``, ``line`` (1-based, or None) and ``message``
    are kept as attributes.

    Several mistakes of one file travel as one error: the first, then ``more`` (one line each) and, past the cap,
    a last line counting the ``left_out`` ones."""

    def __init__(
        self,
        message: str,
        *,
        source: str,
        line: int | None,
        more: Sequence[FileError] = (),
        left_out: int = 0,
    ) -> None:
        self.message = re.sub(r"\s*\n\s*", " ", message).strip()
        self.source = source
        self.line = line
        self.more = tuple(more)
        self.left_out = left_out
        where = source if line is None else f"{source}:{line}"
        lines = [f"{where}: {self.message}", *(str(error) for error in self.more)]
        if left_out:
            lines.append(f"{source}: ... and {left_out} more mistakes")
        super().__init__("\n".join(lines))


MAX_FAULTS = 10  # mistakes reported at once: enough for a file typed by hand, short enough to read


class Mistakes:
    """The mistakes of one file noted so far. A reader that meets a mistake notes it and goes on with what does not
    depend on the faulty value, so that one reading reports every independent mistake (:meth:`Document.attempt`)."""

    def __init__(self) -> None:
        self.found: list[FileError] = []
        # Every note, repeats included: whether a step went wrong, even where its mistake was already found (a
        # top-level key read again for each part of a matrix).
        self.noted = 0

    def note(self, error: FileError) -> None:
        self.noted += 1
        seen = {(found.source, found.line, found.message) for found in self.found}
        for one in (error, *error.more):
            if (one.source, one.line, one.message) not in seen:
                seen.add((one.source, one.line, one.message))
                self.found.append(one)

    def raise_all(self, error_type: type[FileError]) -> None:
        """Raise the mistakes found, in line order (up to :data:`MAX_FAULTS`, then how many more), as one error."""
        if not self.found:
            return
        ordered = sorted(self.found, key=lambda error: error.line or 0)  # stable: reading order within a line
        first, *more = ordered[:MAX_FAULTS]
        left_out = max(0, len(ordered) - MAX_FAULTS)
        raise error_type(first.message, source=first.source, line=first.line, more=more, left_out=left_out)


@dataclass(frozen=True)
class Document:
    """A YAML file as plain data (an empty file is an empty mapping), with the 1-based line of each value and
    each mapping key by path. ``error_type`` is what :meth:`error` raises."""

    source: str
    data: Any
    value_lines: dict[Path, int]
    key_lines: dict[Path, int]
    error_type: type[FileError] = FileError
    mistakes: Mistakes = field(default_factory=Mistakes, compare=False, repr=False)

    def line(self, path: Path) -> int:
        """The line of the value at ``path``, else of the nearest value above it that the file holds."""
        while path not in self.value_lines and path:
            path = path[:-1]
        return self.value_lines.get(path, 1)

    def key_line(self, path: Path) -> int:
        """The line of the key written for the value at ``path`` (where the value starts on a later line)."""
        return self.key_lines.get(path) or self.line(path)

    def error(self, path: Path, message: str, *, at_key: bool = False) -> FileError:
        line = self.key_line(path) if at_key else self.line(path)
        return self.error_type(message, source=self.source, line=line)

    def attempt(self, read: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T | None:
        """``read(*args, **kwargs)``, or None once the mistake it raised is noted (:meth:`raise_noted` raises
        every noted mistake). The caller goes on without the value, checking only what does not depend on it."""
        try:
            return read(*args, **kwargs)
        except FileError as error:
            self.mistakes.note(error)
            return None

    def note(self, error: FileError) -> None:
        """Note a mistake and go on (:meth:`raise_noted` raises it with the others)."""
        self.mistakes.note(error)

    @property
    def noted(self) -> int:
        """How many mistakes were noted so far (repeats included): compare before and after a step to learn whether
        it went wrong."""
        return self.mistakes.noted

    def raise_noted(self) -> None:
        """Raise every mistake noted so far as one error (``error_type``), one line each in line order."""
        self.mistakes.raise_all(self.error_type)


@dataclass(frozen=True)
class Fault:
    """Where a value does not fit its type (``path`` from the top; ``at_key``: the key itself is the mistake) and
    what is wrong, as one sentence."""

    path: Path
    message: str
    at_key: bool = False


def line_of(node: yaml.Node) -> int:
    return node.start_mark.line + 1


def compose(text: str, *, source: str, error_type: type[FileError] = FileError) -> Document:
    """Read ``text`` as YAML (1.1, safe tags only) into plain data, keeping each value's line."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        line = 1 if mark is None else mark.line + 1
        raise error_type(f"invalid YAML: {error.problem or error.context}", source=source, line=line) from None
    except yaml.YAMLError as error:  # a character YAML does not allow: a position, no mark
        position = getattr(error, "position", None)
        line = 1 if position is None else text.count("\n", 0, position) + 1
        raise error_type(f"invalid YAML: {error}", source=source, line=line) from None
    builder = _Builder(source=source, error_type=error_type)
    data = {} if root is None else builder.build(root, ())
    return Document(
        source=source, data=data, value_lines=builder.value_lines, key_lines=builder.key_lines, error_type=error_type
    )


class _Builder:
    """Plain data from YAML nodes, recording lines; duplicate keys and tags the safe loader refuses fail here."""

    def __init__(self, *, source: str, error_type: type[FileError]) -> None:
        self.source = source
        self.error_type = error_type
        self.value_lines: dict[Path, int] = {}
        self.key_lines: dict[Path, int] = {}
        self.constructor = SafeConstructor()
        self.building: set[int] = set()  # nodes being built: an alias of one of them is a cycle

    def error(self, node: yaml.Node, message: str) -> FileError:
        return self.error_type(message, source=self.source, line=line_of(node))

    def build(self, node: yaml.Node, path: Path) -> Any:
        self.value_lines.setdefault(path, line_of(node))
        if id(node) in self.building:
            raise self.error(node, "an alias that contains itself")
        self.building.add(id(node))
        try:
            if isinstance(node, yaml.MappingNode):
                return self._mapping(node, path)
            if isinstance(node, yaml.SequenceNode):
                if node.tag != _SEQ_TAG:
                    raise self.error(node, f"cannot read this value: unknown tag {node.tag!r}")
                return [self.build(item, (*path, index)) for index, item in enumerate(node.value)]
            return self._scalar(node)
        finally:
            self.building.discard(id(node))

    def _mapping(self, node: yaml.MappingNode, path: Path) -> dict[Any, Any]:
        if node.tag != _MAP_TAG:
            raise self.error(node, f"cannot read this value: unknown tag {node.tag!r}")
        first: dict[Any, int] = {}
        for key_node, _ in node.value:  # written keys only: a merged (<<) key may be overridden
            if key_node.tag == _MERGE_TAG:
                continue
            key = self._key(key_node)
            if key in first:
                raise self.error(key_node, f"duplicate key {key!r} (first on line {first[key]})")
            first[key] = line_of(key_node)
        self.constructor.flatten_mapping(node)  # merge keys (<<: *base) become ordinary entries
        result: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = self._key(key_node)
            self.key_lines[(*path, key)] = line_of(key_node)
            self.value_lines.pop((*path, key), None)  # a written key overrides a merged one: its line wins
            result[key] = self.build(value_node, (*path, key))
            if isinstance(value_node, yaml.CollectionNode):  # a block under its key: the key's line names it best
                self.value_lines[(*path, key)] = line_of(key_node)
        return result

    def _key(self, node: yaml.Node) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            raise self.error(node, "a key must be a single value, not a mapping or a list")
        return self._scalar(node)

    def _scalar(self, node: yaml.Node) -> Any:
        try:
            return self.constructor.construct_object(node, deep=True)
        except yaml.YAMLError as error:  # a tag the safe loader does not know (!!python/object, !custom)
            problem = getattr(error, "problem", None) or error
            raise self.error(node, f"cannot read this value: {problem}") from None


def convert(
    data: Any,
    type_: type[T],
    *,
    document: Document,
    path: Path = (),
    what: str = "the file",
) -> T:
    """``msgspec.convert(data, type_)``, where ``data`` sits at ``path`` in ``document``; a value that does not fit
    raises ``document.error_type`` at its line. ``what`` names the top level in messages ("the matrix")."""
    try:
        return msgspec.convert(data, type_)
    except msgspec.ValidationError as error:
        faults = _every_fault(explain(error, type_, data, path=path, what=what), data, type_, path=path, what=what)
    first, *more = [document.error(fault.path, fault.message, at_key=fault.at_key) for fault in faults]
    # One line per mistake, the first as before; the CLI prints them all.
    raise document.error_type(first.message, source=first.source, line=first.line, more=more)


def _every_fault(fault: Fault, data: Any, type_: Any, *, path: Path, what: str) -> list[Fault]:
    """``fault`` and the next ones msgspec finds once each faulty value is left out (up to :data:`MAX_FAULTS`).

    msgspec stops at the first mistake; leaving that value out and converting again finds the next. A value whose
    absence is itself a mistake ("is missing") ends the search: that would report our removal, not the file."""
    faults = [fault]
    while len(faults) < MAX_FAULTS and "is missing" not in fault.message:
        data = _without(data, fault.path[len(path) :])
        if data is None:
            break
        try:
            msgspec.convert(data, type_)
            break
        except msgspec.ValidationError as error:
            fault = explain(error, type_, data, path=path, what=what)
        if fault in faults or "is missing" in fault.message:
            break
        faults.append(fault)
    return faults


def _without(data: Any, relative: Path) -> Any:
    """A copy of ``data`` without the value at ``relative`` (None where there is no such value to leave out)."""
    if not relative:
        return None
    head, rest = relative[0], relative[1:]
    if isinstance(data, dict) and head in data:
        inner = {key: value for key, value in data.items() if key != head}
        if rest:
            child = _without(data[head], rest)
            if child is None:
                return None
            inner[head] = child
        return inner
    if isinstance(data, list) and isinstance(head, int) and 0 <= head < len(data):
        if not rest:
            return None  # leaving an item out would shift the others' paths and lines
        child = _without(data[head], rest)
        return None if child is None else [*data[:head], child, *data[head + 1 :]]
    return None


def unknown_keys(data: Any, type_: Any, *, path: Path = (), what: str = "the file") -> list[Fault]:
    """Every key of ``data`` (at ``path``) that ``type_`` has no field for, however deep: msgspec ignores unknown
    keys of a struct that does not forbid them (a wire type that must read newer senders), and stops at the first
    of one that does; a file typed by hand wants each misspelt key named at its line."""
    chosen = _choose(type_, data)
    if isinstance(data, list):
        return [
            fault
            for index, item in enumerate(data)
            for fault in unknown_keys(item, _item_type(chosen), path=(*path, index), what=what)
        ]
    if not isinstance(data, dict):
        return []
    if get_origin(chosen) is dict:
        item_type = _dict_types(chosen)[1]
        return [
            fault for key, item in data.items() for fault in unknown_keys(item, item_type, path=(*path, key), what=what)
        ]
    if not _is_struct(chosen) or sum(map(_is_struct, _members(type_))) > 1:
        return []  # a tagged union: msgspec picks the member by its tag and reports that member's keys itself
    names = _field_names(chosen, data)
    faults = []
    for key, item in data.items():
        if key in names:
            faults += unknown_keys(item, _field_type(chosen, key), path=(*path, key), what=what)
            continue
        subject = display(path) or what
        message = f"unknown key {key!r} in {subject} (allowed: {', '.join(names)}){did_you_mean(key, names)}"
        faults.append(Fault((*path, key), message, at_key=True))
    return faults


def bound_faults(data: Any, bounds: dict[str, msgspec.Meta], *, path: Path) -> list[Fault]:
    """Each number of the mapping ``data`` (at ``path``) outside its bound in ``bounds``, at its own line: a struct
    that checks its bounds in ``__post_init__`` fails as a whole, at the line of the mapping, and at the first only."""
    if not isinstance(data, dict):
        return []
    faults = []
    for name, bound in bounds.items():
        value = data.get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue  # a value of the wrong type is msgspec's to report
        inside = (
            (bound.ge is None or value >= bound.ge)
            and (bound.gt is None or value > bound.gt)
            and (bound.le is None or value <= bound.le)
            and (bound.lt is None or value < bound.lt)
        )
        if not inside:
            faults.append(Fault((*path, name), f"{display((*path, name))} must be {bound_text(bound)}, got {value}"))
    return faults


def without(data: Any, paths: Sequence[Path]) -> Any:
    """A copy of ``data`` without the values at ``paths`` (each relative to ``data``), where they can be left out
    (not a list's item itself: that would shift the others)."""
    for relative in paths:
        left = _without(data, relative)
        data = data if left is None else left
    return data


def explain(error: msgspec.ValidationError, type_: Any, data: Any, *, path: Path = (), what: str = "the file") -> Fault:
    """msgspec's ``error`` from converting ``data`` (at ``path``) to ``type_``, as the path of the value at fault
    and a sentence naming it."""
    text = str(error)
    match = _AT.search(text)
    text = text[: match.start()] if match else text
    relative, value, value_type = _resolve(data, type_, "$" if match is None else match[1])
    where = (*path, *relative)
    subject = display(where) or what
    if match and "` in `" in match.group(0):  # a key of a mapping does not fit the key type
        return _key_fault(value, value_type, where, subject)
    field = re.fullmatch(r"Object (contains unknown|missing required) field `([^`]*)`", text)
    if field:
        if field[1] == "missing required":
            return Fault(where, f"{subject} is missing {field[2]!r}")
        names = _field_names(value_type, value)
        hint = did_you_mean(field[2], names)
        message = f"unknown key {field[2]!r} in {subject} (allowed: {', '.join(names)}){hint}"
        return Fault((*where, field[2]), message, at_key=True)
    if text.startswith("Invalid enum value"):
        allowed = ", ".join(str(choice) for choice in _literal_values(value_type))
        return Fault(where, f"{subject} must be one of {allowed}, got {value!r}")
    expected = re.fullmatch(r"Expected `([^`]*)`(.*)", text, re.S)
    if expected:
        return Fault(
            where, _expected(expected[1], expected[2], value=value, subject=subject, top=not where, type_=type_)
        )
    return Fault(where, text if not where else f"{text} (at {subject})")


def display(path: Path) -> str:
    """``("brains", 1, "weights")`` -> ``"brains[1].weights"``."""
    text = "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in path)
    return text.removeprefix(".")


def _expected(expected: str, rest: str, *, value: Any, subject: str, top: bool, type_: Any) -> str:
    names = expected.split(" | ")
    if "int" in names and "float" in names:
        names.remove("int")  # "a number" says both
    words = {**_TYPE_WORDS, "bool": "a boolean"} if len(names) > 1 else _TYPE_WORDS
    kinds = " or ".join(words.get(kind, f"`{kind}`") for kind in names)
    kinds = re.sub(r" or (?=.* or )", ", ", kinds)  # "text, a mapping or nothing"
    got = re.fullmatch(r", got `([^`]*)`", rest)
    if got and top and got[1] != "object":
        return f"the top level must be a mapping (keys: {', '.join(_field_names(type_, {}))})"
    if got and got[1] == "null":
        return f"{subject} is empty (expected {kinds})"
    if got:
        return f"{subject} must be {kinds}, got {_shown(value)}"
    length = re.fullmatch(r" of length ([<>]=) (\d+)", rest)
    if length:
        unit = "characters" if expected == "str" else "items"
        if length[1] == ">=" and length[2] == "1":
            return f"{subject} is empty (give at least one)" if unit == "items" else f"{subject} must not be empty"
        bound = "at least" if length[1] == ">=" else "at most"
        return f"{subject} must have {bound} {length[2]} {unit}, got {_shown(value)}"
    pattern = re.fullmatch(r" matching regex (.*)", rest)
    if pattern:
        return f"{subject} must match the pattern {pattern[1]}, got {_shown(value)}"
    return f"{subject} must be {kinds}{rest}, got {_shown(value)}"


def _key_fault(mapping: Any, mapping_type: Any, where: Path, subject: str) -> Fault:
    key_type = _dict_types(mapping_type)[0]
    for key in mapping if isinstance(mapping, dict) else ():
        if not _fits(key, key_type):
            return Fault((*where, key), f"keys of {subject} must be text, got {key!r}", at_key=True)
    return Fault(where, f"a key of {subject} does not fit")


def _shown(value: Any) -> str:
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, bool):
        return "true" if value else "false"  # as YAML writes them
    return repr(value)


# -- walking a type beside the data ----------------------------------------------------------------------------


def _resolve(data: Any, type_: Any, at: str) -> tuple[Path, Any, Any]:
    """msgspec's ``$.parts[...].reps`` -> (the concrete path, the value there, its type). ``[...]`` (a mapping's
    value) is the first entry that does not convert: msgspec stops at the first mistake in written order."""
    path: list[Hashable] = []
    value, value_type = data, type_
    for name, index in _SEGMENT.findall(at):
        chosen = _choose(value_type, value)
        if name and isinstance(value, dict) and name in value:
            path.append(name)
            value, value_type = value[name], _field_type(chosen, name)
        elif index.isdigit() and isinstance(value, list) and int(index) < len(value):
            path.append(int(index))
            value, value_type = value[int(index)], _item_type(chosen)
        elif index == "..." and isinstance(value, dict):
            item_type = _dict_types(chosen)[1]
            key = next((key for key, item in value.items() if not _fits(item, item_type)), None)
            if key is None:
                break
            path.append(key)
            value, value_type = value[key], item_type
        else:
            break
    return tuple(path), value, _choose(value_type, value)


def _fits(value: Any, type_: Any) -> bool:
    try:
        msgspec.convert(value, type_)
    except msgspec.ValidationError:
        return False
    return True


def _members(type_: Any) -> list[Any]:
    while get_origin(type_) is Annotated:
        type_ = get_args(type_)[0]
    if get_origin(type_) in (Union, types.UnionType):
        return [member for arg in get_args(type_) for member in _members(arg)]
    return [type_]


def _is_struct(type_: Any) -> bool:
    return isinstance(type_, type) and issubclass(type_, msgspec.Struct)


def _choose(type_: Any, value: Any) -> Any:
    """The member of a union (Annotated removed) that a value of this kind would convert to."""
    members = _members(type_)
    for member in members:
        origin = get_origin(member) or member
        if isinstance(value, dict) and (_is_struct(member) or origin is dict):
            return member
        if isinstance(value, list) and origin in (list, tuple, set, frozenset):
            return member
        if origin is Literal:
            return member
    return members[0] if len(members) == 1 else type_


def _field_type(type_: Any, name: str) -> Any:
    if _is_struct(type_):
        for field in msgspec.structs.fields(type_):
            if field.encode_name == name:
                return field.type
    if get_origin(type_) is dict:
        return _dict_types(type_)[1]
    return Any


def _item_type(type_: Any) -> Any:
    args = get_args(type_)
    return args[0] if args else Any


def _dict_types(type_: Any) -> tuple[Any, Any]:
    args = get_args(type_)
    return (args[0], args[1]) if len(args) == 2 else (Any, Any)


def _field_names(type_: Any, value: Any) -> list[str]:
    struct = _choose(type_, value if isinstance(value, dict) else {})
    return [field.encode_name for field in msgspec.structs.fields(struct)] if _is_struct(struct) else []


def _literal_values(type_: Any) -> tuple[Any, ...]:
    return tuple(value for member in _members(type_) if get_origin(member) is Literal for value in get_args(member))
