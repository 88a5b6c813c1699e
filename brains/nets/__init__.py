"""The paper's four networks ("Memory based neural networks for end-to-end autonomous driving") and ours, one folder
each: ``<name>/__init__.py`` declares ``INFO``, ``<name>/model.py`` the torch module; :data:`NETWORKS` lists them.

This module is torch-free: ``MODELS`` describes every network (input size, frames, crop, reference parameter
count) so that recorders and brains can prepare inputs without loading torch. ``make_model`` imports the model
module, and with it torch, only when called.
"""

from __future__ import annotations

import importlib
from typing import Any

from brains.nets import deepest_lstm_tiny_pilotnet, memdccp, pilotnet, pilotnet_x3, recurrent_tiny_pilotnet
from brains.nets.info import ModelInfo

# One line per network: each folder declares its INFO (input, frames, crop, model class, reference parameter count)
# and holds its model; the brain of the same name, the contract tests and training all follow from this tuple.
NETWORKS: tuple[ModelInfo, ...] = (
    pilotnet.INFO,
    deepest_lstm_tiny_pilotnet.INFO,
    pilotnet_x3.INFO,
    memdccp.INFO,
    recurrent_tiny_pilotnet.INFO,
)
MODELS: dict[str, ModelInfo] = {info.name: info for info in NETWORKS}


def make_model(name: str, **hyper: Any):
    """A freshly initialised ``torch.nn.Module`` for network ``name``; ``hyper`` goes to its constructor."""
    try:
        info = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown network {name!r} (known: {', '.join(sorted(MODELS))})") from None
    module_name, class_name = info.module.split(":")
    return getattr(importlib.import_module(module_name), class_name)(**hyper)


__all__ = ["MODELS", "NETWORKS", "ModelInfo", "make_model"]
