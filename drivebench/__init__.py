"""drivebench as a Python library for reinforcement learning: importing it registers the Gymnasium environments.

    import gymnasium as gym
    import drivebench

    env = gym.make("drivebench/LaneFollow-v0", circuit="simple", camera=(96, 96))

The environment needs the ``rl`` extra (``pip install drivebench[rl]``); without gymnasium installed this import
registers nothing and costs nothing.
"""

from __future__ import annotations

ENV_IDS = ("drivebench/LaneFollow-v0",)


def _register() -> None:
    try:
        import gymnasium
    except ImportError:  # the rl extra is not installed
        return
    if ENV_IDS[0] not in gymnasium.registry:
        gymnasium.register(id=ENV_IDS[0], entry_point="drivebench.rl.env:LaneFollowEnv")


_register()
