"""Progress of one episode on stderr (``drivebench run``, ``dataset collect``): lap progress, sim time, RTF.

Its own module so that library code (``orchestrator.collect``) shows it without importing the CLI.
"""

from __future__ import annotations

import sys

from protocol.messages import LiveMetrics


class EpisodeProgress:
    """Lap progress, sim time and real-time factor on stderr while an episode runs."""

    def __init__(self, laps: int, *, enabled: bool):
        from tqdm import tqdm

        self._bar = tqdm(
            total=100 * laps,
            unit="%",
            file=sys.stderr,
            disable=not enabled,
            dynamic_ncols=True,
            bar_format="lap progress {percentage:3.0f}%|{bar}| {desc}",
        )

    def update(self, live: LiveMetrics) -> None:
        self._bar.n = min(self._bar.total, round(100 * live.progress_laps, 1))
        self._bar.set_description_str(
            f"lap {min(live.completed_laps + 1, live.laps_target)}/{live.laps_target}  "
            f"sim {live.sim_time_s:6.1f} s  RTF {live.real_time_factor:4.1f}x  "
            f"|xte| {live.cross_track_m:4.2f} m",
            refresh=True,
        )

    def close(self) -> None:
        self._bar.close()
