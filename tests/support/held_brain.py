"""A test brain that holds its episode still until the test lets it go, so that whatever a test does "mid-episode"
(kill the brain, swap it, join a viewer) provably lands inside the episode, however fast or loaded the machine.

In lock-step the simulator waits for the active brain's answer to every frame, so a brain that does not answer
freezes its episode's simulated time: :class:`HeldBrain` drives like the constant brain until its frames reach
``hold_at_s`` of simulated time, writes its pid to ``held`` and then waits for the file ``release`` to exist before it
answers again. The test acts once ``held`` exists (a :class:`Hold` reads it) and creates ``release`` after. Timing
plays no part: before ``held`` exists the episode is not yet at ``hold_at_s``; until ``release`` exists it cannot end.

Brain hosts import it as ``support.held_brain:HeldBrain`` (a module path): the test gives its stack processes
:func:`pythonpath_with_support` as ``PYTHONPATH`` (the launcher and Ray's workers pass their environment on).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brains.base import Action, Observation
from brains.registry import make_brain

TARGET = "support.held_brain:HeldBrain"
TESTS_DIR = Path(__file__).resolve().parent.parent  # where ``support`` is a package, as pytest sees it
POLL_S = 0.02
# Longer than any test waits for its hold; a brain still held by then answers again, so a test that never acted
# fails on its own assertions instead of hanging its episode.
MAX_HOLD_S = 120.0


def pythonpath_with_support() -> str:
    """``PYTHONPATH`` for a child that must import ``support.held_brain``: tests/ first, then the current value."""
    return os.pathsep.join(filter(None, [str(TESTS_DIR), os.environ.get("PYTHONPATH", "")]))


class HeldBrain:
    """Drives as the registered brain ``brain`` built with ``options`` (the constant brain by default); in its episode
    number ``hold_in_episode`` (0: the first it drives), at the first frame at or past ``hold_at_s`` (simulated
    seconds since the episode start), it writes its pid to the file ``held`` and waits until the file ``release``
    exists (at most ``max_hold_s`` wall seconds) before answering. A brain that reaches its hold after the release
    drives through."""

    def __init__(
        self,
        *,
        held: str,
        release: str,
        hold_at_s: float = 2.0,
        hold_in_episode: int = 0,
        brain: str = "constant",
        max_hold_s: float = MAX_HOLD_S,
        **options: Any,
    ):
        self._inner = make_brain(brain, **options)
        self._held, self._release = Path(held), Path(release)
        self._hold_at_ns = int(float(hold_at_s) * 1e9)
        self._hold_in_episode = int(hold_in_episode)
        self._max_hold_s = float(max_hold_s)
        self._episodes = 0  # episodes this process began (a warm stack's brain drives several)
        self._done = False

    def reset(self, *, seed: int) -> None:
        self._episodes += 1
        self._inner.reset(seed=seed)

    def act(self, observation: Observation) -> Action:
        # One hold per brain process, in its hold_in_episode-th episode (counted from 0).
        if not self._done and self._episodes == self._hold_in_episode + 1 and observation.stamp_ns >= self._hold_at_ns:
            self._done = True
            self._hold()
        return self._inner.act(observation)

    def _hold(self) -> None:
        if self._release.exists():
            return
        partial = self._held.with_suffix(".partial")
        partial.write_text(str(os.getpid()))
        partial.replace(self._held)  # whole or absent: the test never reads half a pid
        deadline = time.monotonic() + self._max_hold_s
        while not self._release.exists() and time.monotonic() < deadline:
            time.sleep(POLL_S)


@dataclass(frozen=True)
class Hold:
    """The test's side of a :class:`HeldBrain`: its two files in ``folder``, and what to put in a matrix file."""

    folder: Path

    @property
    def held_path(self) -> Path:
        return self.folder / "held"

    @property
    def release_path(self) -> Path:
        return self.folder / "release"

    def options(self, *, hold_at_s: float, **brain: object) -> dict[str, object]:
        """A :class:`HeldBrain`'s options: these files, the hold's sim time, and ``brain``'s (its name and options)."""
        return {"held": str(self.held_path), "release": str(self.release_path), "hold_at_s": hold_at_s, **brain}

    def launch_options(self, *, hold_at_s: float, **brain: object) -> tuple[str, ...]:
        """The same as ``key=value`` overrides, for a :class:`~orchestrator.stack.launcher.BrainLaunch`."""
        return tuple(f"{key}={json.dumps(value)}" for key, value in self.options(hold_at_s=hold_at_s, **brain).items())

    def held_pid(self) -> int | None:
        """The pid of the brain holding its episode now, or None while none has reached its hold."""
        try:
            return int(self.held_path.read_text())
        except (FileNotFoundError, ValueError):
            return None

    def release(self) -> None:
        self.release_path.touch()
