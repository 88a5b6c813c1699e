"""One loader for every process config: a YAML file plus ``key.path=value`` overrides, checked against a struct.

Errors are one line naming the file, the line and the field (``simulator.yaml:3: bus.lease_ms must be an integer,
got 'soon'``), or ``command line:`` for a value an override set, so a typo in a config never surfaces as a
traceback deep inside a service.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import yaml

from protocol.deploy.typed_yaml import Document, Fault, FileError, compose, explain

T = TypeVar("T")


class ConfigError(ValueError):
    """A config file or override that does not fit the config type; the text names where and which field."""


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"bus.lease_ms=2000"`` -> (["bus", "lease_ms"], 2000). The value is parsed as YAML (``[a, b]``, ``true``)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like key.path=value")
    path, _, raw = text.partition("=")
    keys = [k for k in path.strip().split(".") if k]
    if not keys:
        raise ConfigError(f"override {text!r} has an empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as error:
        raise ConfigError(f"override {text!r}: value is not valid YAML ({error})") from None
    return keys, value


def apply_overrides(data: dict[str, Any], overrides: Iterable[str]) -> dict[str, Any]:
    for text in overrides:
        keys, value = parse_override(text)
        node = data
        for key in keys[:-1]:
            child = node.get(key)
            if not isinstance(child, dict):
                child = node[key] = {}
            node = child
        node[keys[-1]] = value
    return data


def read_yaml_document(path: Path) -> Document:
    """The config file at ``path``, a mapping (empty for an empty file), with the line of every value."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"cannot read config {path}: {error.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not UTF-8 text") from None
    try:
        document = compose(text, source=str(path))
    except FileError as error:
        raise ConfigError(str(error)) from None
    if not isinstance(document.data, dict):
        got = "a list" if isinstance(document.data, list) else repr(document.data)
        raise ConfigError(f"{path}:{document.line(())}: expected a mapping at the top level, got {got}")
    return document


def load_config(
    config_type: type[T],
    *,
    path: str | Path | None = None,
    overrides: Iterable[str] = (),
    base: dict[str, Any] | None = None,
) -> T:
    """Build ``config_type`` from ``base`` <- the YAML file at ``path`` <- ``overrides`` (later wins)."""
    data: dict[str, Any] = dict(base or {})
    document = None
    if path is not None:
        document = read_yaml_document(Path(path))
        data.update(document.data)
    overrides = list(overrides)
    apply_overrides(data, overrides)
    try:
        return msgspec.convert(data, config_type)
    except msgspec.ValidationError as error:
        fault = explain(error, config_type, data, what="the config")
        set_paths = [tuple(parse_override(text)[0]) for text in overrides]
        raise ConfigError(_where(fault, document, set_paths) + fault.message) from None


def _where(fault: Fault, document: Document | None, set_paths: list[tuple[str, ...]]) -> str:
    """``FILE:LINE: `` for a value the file wrote, ``command line: `` for one an override set (or set inside)."""
    path = fault.path
    if any(path[: len(keys)] == keys for keys in set_paths):
        return "command line: "
    if document is not None and (not path or path[0] in document.data):
        line = document.key_line(path) if fault.at_key else document.line(path)
        return f"{document.source}:{line}: "
    if any(keys[: len(path)] == path for keys in set_paths):
        return "command line: "
    return "command line: " if document is None else f"{document.source}: "


def dump_config(config: Any) -> str:
    """The resolved config as YAML (logged at start, written into run folders and recordings)."""
    return yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False)
