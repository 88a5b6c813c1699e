"""Episode trajectories and circuit drawings for the report: :func:`load_trajectory` reads an episode's ``.npz``
file, :class:`Track` holds a circuit's road edges and extent, :func:`speeds_mps` the speed at each pose.

Separate from the plots (:mod:`orchestrator.report.plots`) so that loading and geometry are not tied to matplotlib:
the report's data access (:class:`orchestrator.report.data.ReportData`) reads and caches them, the plots only draw.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# -- trajectories and circuits ----------------------------------------------------------------------------------------


TRAJECTORY_ARRAYS = (
    "stamp_s",
    "x_m",
    "y_m",
    "yaw_rad",
    "speed_mps",
    "live_sim_time_s",
    "live_progress_laps",
    "live_cross_track_m",
)


def load_trajectory(folder: Path, relative: str | None) -> dict[str, np.ndarray] | None:
    """The episode's trajectory arrays (every name of :data:`TRAJECTORY_ARRAYS`, empty when absent), or None when
    there is no file or it cannot be read."""
    if not relative:
        return None
    path = folder / relative
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {
                name: np.asarray(data[name], dtype=float).ravel() if name in data.files else np.zeros(0)
                for name in TRAJECTORY_ARRAYS
            }
    except Exception:  # a damaged file (BadZipFile, ValueError, OSError...) only loses its plot
        return None
    n = min(len(arrays["x_m"]), len(arrays["y_m"]))
    arrays["x_m"], arrays["y_m"] = arrays["x_m"][:n], arrays["y_m"][:n]
    return arrays


class Track:
    """A circuit's drawing: its points, road edges and extent (cross-track colours come from its centreline)."""

    def __init__(self, circuit):
        self.circuit = circuit
        self.points = circuit.centreline.points_m
        normals = circuit.centreline.left_normals()
        half = circuit.road_half_width_m
        self.left_edge = self.points + half * normals
        self.right_edge = self.points - half * normals
        self.half_width_m = half
        margin = half + 3.0
        self.extent = (
            float(self.points[:, 0].min() - margin),
            float(self.points[:, 0].max() + margin),
            float(self.points[:, 1].min() - margin),
            float(self.points[:, 1].max() + margin),
        )

    def lateral_m(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Signed distance (+ left) of each point to the centreline, for colouring a plot."""
        return self.circuit.centreline.project_many(x_m, y_m)[1]


def speeds_mps(trajectory: dict[str, np.ndarray]) -> np.ndarray:
    """Speed at each pose: the recorded one, else from successive positions and stamps."""
    x, y = trajectory["x_m"], trajectory["y_m"]
    speed = trajectory["speed_mps"]
    if len(speed) == len(x):
        return speed
    stamps = trajectory["stamp_s"]
    if len(stamps) == len(x) and len(x) >= 2:
        dt = np.diff(stamps)
        step = np.hypot(np.diff(x), np.diff(y)) / np.where(dt > 0, dt, np.nan)
        return np.nan_to_num(np.concatenate([[step[0]], step]))
    return np.zeros(len(x))
