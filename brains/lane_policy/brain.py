"""The lane-following RL policy as a drivebench brain: camera image -> line features -> a small MLP -> command.

The policy file (``.npz``, written by ``drivebench.rl.policy.export_sb3``) holds the deterministic actor of a
Stable-Baselines3 SAC or PPO policy as plain arrays (``w0, b0, w1, b1, ...``: ReLU between layers, tanh on the
output for SAC, clipping for PPO) and a JSON ``meta`` with the action ranges the environment mapped actions to.
Serving it needs NumPy only, no torch and no Stable-Baselines3; the forward pass is a few small matrix products.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from brains.base import Action, Observation
from brains.lane_policy.features import FEATURES, line_features, scaled
from brains.registry import BrainOptionsError

SHIPPED_POLICY = Path(__file__).resolve().parent.parent / "weights" / "lane_policy.npz"


class PolicyFileError(BrainOptionsError):
    """A policy file that cannot be served: one line, naming the file and what is wrong."""


class LanePolicyBrain:
    """Drives with the exported RL policy in ``weights`` (default: the one drivebench ships)."""

    def __init__(self, *, weights: str | None = None):
        path = Path(weights) if weights else SHIPPED_POLICY
        self.layers, self.meta = load_policy(path)
        self.speed_range_mps = tuple(self.meta["speed_range_mps"])
        self.yaw_rate_range_radps = tuple(self.meta["yaw_rate_range_radps"])
        self.reset(seed=0)

    @staticmethod
    def preflight(*, weights: str | None = None) -> None:
        """Check the policy file before any process starts (PolicyFileError, one line)."""
        load_policy(Path(weights) if weights else SHIPPED_POLICY)

    def reset(self, *, seed: int) -> None:
        del seed  # deterministic
        self._previous_action = np.zeros(2)

    def act(self, observation: Observation) -> Action:
        features = line_features(observation.image_rgb, previous_action=self._previous_action)
        action = policy_action(self.layers, features, squash=self.meta.get("squash", "tanh"))
        self._previous_action = action
        return Action(
            speed_mps=scaled(action[0], *self.speed_range_mps),
            yaw_rate_radps=scaled(action[1], *self.yaw_rate_range_radps),
        )


def policy_action(layers: list[tuple[np.ndarray, np.ndarray]], features: np.ndarray, *, squash: str) -> np.ndarray:
    """The deterministic action in [-1, 1]^2 of the MLP ``layers`` for one feature vector."""
    hidden = features.astype(np.float64)
    for index, (weight, bias) in enumerate(layers):
        hidden = weight @ hidden + bias
        if index < len(layers) - 1:
            hidden = np.maximum(hidden, 0.0)
    return np.tanh(hidden) if squash == "tanh" else np.clip(hidden, -1.0, 1.0)


def load_policy(path: Path) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict]:
    """The layers and metadata of a policy file; :class:`PolicyFileError` when it is not one."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            layers = [
                (data[f"w{i}"].astype(np.float64), data[f"b{i}"].astype(np.float64)) for i in range(meta["layers"])
            ]
    except (OSError, KeyError, ValueError) as error:
        raise PolicyFileError(f"lane_policy: {path} is not a policy file ({error})") from None
    if layers[0][0].shape[1] != FEATURES or layers[-1][0].shape[0] != 2:
        raise PolicyFileError(
            f"lane_policy: {path} maps {layers[0][0].shape[1]} features to "
            f"{layers[-1][0].shape[0]} actions, expected {FEATURES} -> 2"
        )
    return layers, meta
