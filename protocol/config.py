"""One loader for every process config: a YAML file plus ``key.path=value`` overrides, checked against a struct.

Errors name the file and the field (``simulator.yaml: Expected `int`, got `str` - at `$.bus.lease_ms```), so a
typo in a config never surfaces as a traceback deep inside a service.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import yaml

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


def read_yaml_mapping(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as error:
        raise ConfigError(f"cannot read config {path}: {error.strerror}") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def load_config(
    config_type: type[T],
    *,
    path: str | Path | None = None,
    overrides: Iterable[str] = (),
    base: dict[str, Any] | None = None,
) -> T:
    """Build ``config_type`` from ``base`` <- the YAML file at ``path`` <- ``overrides`` (later wins)."""
    data: dict[str, Any] = dict(base or {})
    source = "command line"
    if path is not None:
        data.update(read_yaml_mapping(Path(path)))
        source = str(path)
    apply_overrides(data, overrides)
    try:
        return msgspec.convert(data, config_type)
    except msgspec.ValidationError as error:
        raise ConfigError(f"{source}: {error}") from None


def dump_config(config: Any) -> str:
    """The resolved config as YAML (logged at start, written into run folders and recordings)."""
    return yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False)
