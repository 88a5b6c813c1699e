"""Export a Stable-Baselines3 policy to the plain-array file the ``lane_policy`` brain serves (NumPy only there).

SAC: the actor's ``latent_pi`` MLP and ``mu`` layer, squashed by tanh (SAC's deterministic action). PPO: the
policy MLP and ``action_net``, clipped to [-1, 1] (what SB3 does with a Box action). Imports torch lazily.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def _linear_layers(modules) -> list[tuple[np.ndarray, np.ndarray]]:
    import torch

    return [
        (module.weight.detach().cpu().numpy(), module.bias.detach().cpu().numpy())
        for module in modules
        if isinstance(module, torch.nn.Linear)
    ]


def sb3_layers(model: Any) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    """The deterministic actor of a SAC or PPO model as (weight, bias) layers, and its squash ("tanh"/"clip")."""
    policy = model.policy
    if hasattr(policy, "actor"):  # SAC, TD3-like
        actor = policy.actor
        return _linear_layers(actor.latent_pi) + _linear_layers([actor.mu]), "tanh"
    extractor = policy.mlp_extractor.policy_net
    return _linear_layers(extractor) + _linear_layers([policy.action_net]), "clip"


def export_sb3(model: Any, path: Path, *, speed_range_mps, yaw_rate_range_radps, note: str = "") -> Path:
    """Write ``path`` (.npz): the layers, the squash and the action ranges the environment used."""
    layers, squash = sb3_layers(model)
    meta = {
        "layers": len(layers),
        "squash": squash,
        "speed_range_mps": [float(v) for v in speed_range_mps],
        "yaw_rate_range_radps": [float(v) for v in yaw_rate_range_radps],
        "note": note,
    }
    # Any: savez_compressed's own keyword (allow_pickle) shares the ** with the arrays' names.
    arrays: dict[str, Any] = {"meta": np.array(json.dumps(meta))}
    arrays |= {f"w{i}": w.astype(np.float32) for i, (w, _) in enumerate(layers)}
    arrays |= {f"b{i}": b.astype(np.float32) for i, (_, b) in enumerate(layers)}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path
