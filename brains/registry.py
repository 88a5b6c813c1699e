"""Brains by name, imported lazily so that torch loads only when a neural brain is asked for."""

from __future__ import annotations

import importlib
from typing import Any

from brains.base import Brain

# name -> "module:factory". The factory takes keyword options and returns a Brain.
_REGISTRY: dict[str, str] = {
    "explicit": "brains.explicit.brain:ExplicitBrain",
    "constant": "brains.constant.brain:ConstantBrain",
}


class UnknownBrainError(ValueError):
    pass


def register(name: str, target: str) -> None:
    """Register a brain factory as ``"package.module:callable"`` (imported only when the brain is made)."""
    if ":" not in target:
        raise ValueError(f"brain target must look like 'module:callable', got {target!r}")
    _REGISTRY[name] = target


def brain_names() -> list[str]:
    return sorted(_REGISTRY)


def make_brain(name: str, **options: Any) -> Brain:
    """A new instance of brain ``name`` built with ``options``."""
    target = _REGISTRY.get(name)
    if target is None:
        raise UnknownBrainError(f"unknown brain {name!r} (known: {', '.join(brain_names())})")
    module_name, factory_name = target.split(":")
    factory = getattr(importlib.import_module(module_name), factory_name)
    return factory(**options)
