"""Which brain drove each frame, and how far the others (shadows) were from it: the scorer's pure core (no bus).

Every brain of a run answers the same frames; the simulator applies only the active brain's answer. The driver of
frame n is the episode's first active brain, or the ``to_brain`` of the last switch at or before frame n. Commands
are kept per frame until the frame is settled: its driver's command goes on to the episode's metrics and each
shadow's (a command marked ``shadow``: its host was started as one) to that host's :class:`ShadowDistance`, one per
process (``Command.host``), so two shadows of one name never merge. Brains that are neither (swapped out, or waiting
to be swapped in) are in no list. Settling waits (up to ``max_pending_frames`` frames, or the end of the episode),
because a switch event and the commands around it travel on different keys and may arrive in any order.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass

from protocol.messages import BrainSwitch, Command, ShadowDistance

#: Frames whose commands are kept before the oldest is settled (a few minutes of lock-step at 20 Hz).
MAX_PENDING_FRAMES = 2000


@dataclass
class _Distance:
    """Running sums of one shadow's differences to the driver."""

    frames: int = 0
    speed_abs_sum: float = 0.0
    yaw_rate_abs_sum: float = 0.0
    yaw_rate_sq_sum: float = 0.0
    yaw_rate_max_abs: float = 0.0

    def add(self, speed_diff_mps: float, yaw_rate_diff_radps: float) -> None:
        self.frames += 1
        self.speed_abs_sum += abs(speed_diff_mps)
        self.yaw_rate_abs_sum += abs(yaw_rate_diff_radps)
        self.yaw_rate_sq_sum += yaw_rate_diff_radps**2
        self.yaw_rate_max_abs = max(self.yaw_rate_max_abs, abs(yaw_rate_diff_radps))

    def result(self, brain: str, host: str) -> ShadowDistance:
        n = self.frames
        return ShadowDistance(
            brain=brain,
            host=host,
            frames=n,
            speed_mae_mps=self.speed_abs_sum / n if n else 0.0,
            yaw_rate_mae_radps=self.yaw_rate_abs_sum / n if n else 0.0,
            yaw_rate_rmse_radps=math.sqrt(self.yaw_rate_sq_sum / n) if n else 0.0,
            yaw_rate_max_abs_radps=self.yaw_rate_max_abs,
        )


class CommandMatcher:
    """Commands of one episode matched by frame.

    first_driver: the brain active at the start (the spec's ``active_brain``).
    on_driver: called once per settled frame with the driver's command (in frame order while nothing is late).
    """

    def __init__(
        self, *, first_driver: str, on_driver: Callable[[Command], None], max_pending_frames: int = MAX_PENDING_FRAMES
    ):
        self._first_driver = first_driver
        self._on_driver = on_driver
        self._max_pending = max_pending_frames
        self._pending: dict[int, dict[tuple[str, str], Command]] = {}  # frame -> (brain, host) -> its first answer
        self._settled_below = 0  # every frame below this is settled; later answers to them are dropped
        self._switch_seqs: list[int] = []
        self.switches: list[BrainSwitch] = []
        self._distances: dict[tuple[str, str], _Distance] = {}  # by shadow (brain, host)
        self._last_answered: dict[str, int] = {}  # brain -> the latest frame it answered as a driver could
        self._last_answered_any: dict[str, int] = {}  # brain -> the latest frame it answered, shadows included
        self.late_commands = 0

    def add_switch(self, switch: BrainSwitch) -> None:
        """A BRAIN_SWITCH of this episode: ``switch.to_brain`` drives from frame ``switch.seq`` on."""
        index = bisect.bisect_right(self._switch_seqs, switch.seq)
        self._switch_seqs.insert(index, switch.seq)
        self.switches.insert(index, switch)

    def add_command(self, command: Command) -> None:
        """One brain's answer to frame ``command.frame_seq`` (the first answer per brain host and frame counts)."""
        if not command.shadow:  # a shadow never drives, even under a driver's name
            self._last_answered[command.brain] = max(command.frame_seq, self._last_answered.get(command.brain, -1))
        self._last_answered_any[command.brain] = max(command.frame_seq, self._last_answered_any.get(command.brain, -1))
        if command.frame_seq < self._settled_below:
            self.late_commands += 1
            return
        self._pending.setdefault(command.frame_seq, {}).setdefault((command.brain, command.host), command)
        while len(self._pending) > self._max_pending:
            self._settle(min(self._pending))

    def driver_answered(self, frame_seq: int) -> bool:
        """Whether the driver of frame ``frame_seq`` has answered it (or a later frame); True below frame 0."""
        return frame_seq < 0 or self._last_answered.get(self.driver(frame_seq), -1) >= frame_seq

    def answered(self, brain: str, frame_seq: int) -> bool:
        """Whether brain ``brain`` (a host of that name, shadow or not) has answered frame ``frame_seq`` or a later
        one; True below frame 0."""
        return frame_seq < 0 or self._last_answered_any.get(brain, -1) >= frame_seq

    def driver(self, frame_seq: int) -> str:
        """The brain whose command drove frame ``frame_seq``, from the switches known so far."""
        index = bisect.bisect_right(self._switch_seqs, frame_seq)
        return self.switches[index - 1].to_brain if index else self._first_driver

    def finish(self) -> list[ShadowDistance]:
        """Settle every pending frame; the distance of every shadow host, by brain name and host."""
        for frame_seq in sorted(self._pending):
            self._settle(frame_seq)
        return [self._distances[shadow].result(*shadow) for shadow in sorted(self._distances)]

    def _settle(self, frame_seq: int) -> None:
        answers = self._pending.pop(frame_seq)
        self._settled_below = max(self._settled_below, frame_seq + 1)
        driver = self.driver(frame_seq)
        # The first answer under the driver's name that is not a shadow's (in arrival order, as the simulator took it)
        driving = next((c for (brain, _), c in answers.items() if brain == driver and not c.shadow), None)
        if driving is None:
            return  # the driver's answer never came (real-time mode, or lost): nothing to compare with
        self._on_driver(driving)
        for shadow, command in answers.items():
            if command.shadow:
                self._distances.setdefault(shadow, _Distance()).add(
                    command.speed_mps - driving.speed_mps, command.yaw_rate_radps - driving.yaw_rate_radps
                )
