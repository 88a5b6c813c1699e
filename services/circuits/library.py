"""Circuits by name: data files of control points turned into a centreline and road dimensions."""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import msgspec
import numpy as np
import yaml
from scipy.interpolate import splev, splprep

from services.circuits.centreline import Centreline

RESAMPLE_STEP_M = 0.25


class CircuitError(ValueError):
    """An unknown circuit name or a bad circuit file; the text names which and where."""


class CircuitFile(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The YAML format of a circuit file (see ``services/circuits/data/simple.yaml``)."""

    name: str
    description: str = ""
    source: str = ""
    road_width_m: float = 3.0
    line_width_m: float = 0.10
    wall_height_m: float = 0.5
    control_points_m: list[tuple[float, float]]


@dataclass(frozen=True)
class Circuit:
    """A closed road around a centreline, in driving order.

    road_half_width_m: centre line to road edge (the wall stands on the edge when walls are on).
    The start pose is the first centreline point, heading along the track.
    """

    name: str
    description: str
    source: str
    centreline: Centreline
    road_half_width_m: float
    line_width_m: float
    wall_height_m: float

    @property
    def length_m(self) -> float:
        return self.centreline.length_m

    def start_pose(self) -> tuple[float, float, float]:
        """(x_m, y_m, yaw_rad) of the start, on the centre line facing the driving direction."""
        return self.centreline.pose_at(0.0)


def _data_dir() -> Path:
    return Path(str(resources.files("services.circuits") / "data"))


def circuit_names() -> list[str]:
    return sorted(path.stem for path in _data_dir().glob("*.yaml"))


def load_circuit(name: str) -> Circuit:
    """The built-in circuit ``name``; :class:`CircuitError` names the known ones when it does not exist."""
    path = _data_dir() / f"{name}.yaml"
    if not path.is_file():
        raise CircuitError(f"unknown circuit {name!r} (known: {', '.join(circuit_names())})")
    return circuit_from_file(path)


def circuit_from_file(path: Path) -> Circuit:
    try:
        raw = yaml.safe_load(path.read_text())
        spec = msgspec.convert(raw, CircuitFile)
    except (yaml.YAMLError, msgspec.ValidationError, OSError) as error:
        raise CircuitError(f"{path}: {error}") from None
    if len(spec.control_points_m) < 4:
        raise CircuitError(f"{path}: control_points_m needs at least 4 points, got {len(spec.control_points_m)}")
    points = np.asarray(spec.control_points_m, dtype=float)
    return Circuit(
        name=spec.name,
        description=spec.description,
        source=spec.source,
        centreline=Centreline(closed_spline(points, step_m=RESAMPLE_STEP_M)),
        road_half_width_m=spec.road_width_m / 2,
        line_width_m=spec.line_width_m,
        wall_height_m=spec.wall_height_m,
    )


def closed_spline(control_points_m: np.ndarray, *, step_m: float) -> np.ndarray:
    """A periodic cubic spline through the control points, resampled at (close to) ``step_m`` arc length."""
    closed = np.vstack([control_points_m, control_points_m[:1]])  # splprep(per=1) wants the loop closed
    tck, _ = splprep([closed[:, 0], closed[:, 1]], s=0, per=1)
    dense_u = np.linspace(0.0, 1.0, 50 * len(closed) * 20, endpoint=False)
    dense = np.stack(splev(dense_u, tck), axis=1)
    steps = np.hypot(*np.diff(np.vstack([dense, dense[:1]]), axis=0).T)
    s_dense = np.concatenate([[0.0], np.cumsum(steps)])
    length = s_dense[-1]
    count = max(8, round(length / step_m))
    s_target = np.linspace(0.0, length, count, endpoint=False)
    u_target = np.interp(s_target, s_dense, np.append(dense_u, 1.0))
    return np.stack(splev(u_target, tck), axis=1)
