"""Brains by name, imported lazily so that torch loads only when a neural brain is asked for."""

from __future__ import annotations

import importlib
from typing import Any

from brains.base import Brain

# name -> "module:factory". The factory takes keyword options and returns a Brain.
_REGISTRY: dict[str, str] = {
    "explicit": "brains.explicit.brain:ExplicitBrain",
    "constant": "brains.constant.brain:ConstantBrain",
    "noisy": "brains.noisy.brain:NoisyBrain",
    "expert": "brains.expert.brain:ExpertBrain",  # privileged: pure pursuit on the ground-truth pose
    # The paper's networks, served from a checkpoint (``--weights CKPT``); each checks the checkpoint's model.
    "pilotnet": "brains.neural.brain:pilotnet",
    "deepest_lstm_tiny_pilotnet": "brains.neural.brain:deepest_lstm_tiny_pilotnet",
    "pilotnet_x3": "brains.neural.brain:pilotnet_x3",
    "memdccp": "brains.neural.brain:memdccp",
    "neural": "brains.neural.brain:neural",  # any network: whatever the checkpoint holds
}


class UnknownBrainError(ValueError):
    pass


class BrainOptionsError(ValueError):
    """A brain's options are missing or unusable (no weights, a bad checkpoint): one line, no traceback."""


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
