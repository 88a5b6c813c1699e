"""Circuits by name: data files of control points turned into a centreline and road dimensions.

Three kinds of names:

* **built-in** circuits: ``circuits/data/NAME.yaml``, authored for drivebench at Behavior Metrics' scale;
* **user** circuits: ``NAME.yaml`` files in :func:`user_circuits_dir` (``$DRIVEBENCH_CIRCUITS_DIR``, else
  ``~/.local/share/drivebench/circuits``), e.g. written by :func:`circuits.importer.import_racetrack_csv`.
  They are checked with :func:`check_track` when loaded. A built-in of the same name wins;
* ``random:SEED``: a procedural circuit from :func:`circuits.generator.random_circuit`.
* ``twisty:SEED``: a procedural circuit of straights and hairpins from
  :func:`circuits.generator.twisty_circuit`.
* ``grandprix:SEED``: a procedural circuit laid out like a Grand Prix track (long straights, a hairpin, a chicane)
  from :func:`circuits.generator.grandprix_circuit`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import msgspec
import numpy as np
import yaml

from circuits.centreline import Centreline
from circuits.variables import CIRCUITS_DIR  # stdlib only; listed in the one table, protocol.environment

RESAMPLE_STEP_M = 0.25
RANDOM_PREFIX = "random:"
TWISTY_PREFIX = "twisty:"
GRANDPRIX_PREFIX = "grandprix:"
GENERATED_PREFIXES = (RANDOM_PREFIX, TWISTY_PREFIX, GRANDPRIX_PREFIX)
GENERATED_NAMES = "random:SEED, twisty:SEED or grandprix:SEED"
# The generated families by name prefix, filled in by circuits.generator when the package is imported: the generator
# builds on this module's geometry, so this module must not import it (no import cycle).
GENERATORS: dict[str, Callable[[int], Circuit]] = {}
USER_CIRCUITS_ENV = CIRCUITS_DIR.name
# A circuit name a user may give: letters, digits, '_', '-' and '.', starting with a letter or digit (so no path,
# no hidden file, no "random:" prefix).
PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")

# check_track's default clearance: the walls of two neighbouring parts of the track must stay this far apart.
WALL_CLEARANCE_M = 0.5
# check_track looks at the track resampled at (at most) this spacing.
CHECK_STEP_M = 1.0


class CircuitError(ValueError):
    """An unknown circuit name or a bad circuit file; the text names which and where."""


class CircuitFile(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The YAML format of a circuit file (see ``circuits/data/simple.yaml``)."""

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
    The start line is the first centreline point; an episode may start any distance along the track from it
    (:meth:`start_pose`).
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

    def start_pose(self, *, start_m: float = 0.0) -> tuple[float, float, float]:
        """(x_m, y_m, yaw_rad) of the start, on the centre line facing the driving direction: ``start_m`` metres
        along the track in driving order from the start line (``EpisodeSpec.start_m``). :class:`CircuitError` when
        ``start_m`` is not on the circuit (:meth:`check_start_m`)."""
        self.check_start_m(start_m)
        return self.centreline.pose_at(start_m)

    def check_start_m(self, start_m: float) -> None:
        """:class:`CircuitError` (one line naming the circuit's length) unless 0 <= ``start_m`` < the length: a start
        one length or more along would be a start line that :meth:`Centreline.pose_at` silently wraps round."""
        if not 0.0 <= start_m < self.length_m:  # also refuses NaN
            raise CircuitError(
                f"start_m must be >= 0 and below {self.length_m:g} m, the length of circuit {self.name!r}, "
                f"got {start_m:g}"
            )

    def reversed(self) -> Circuit:
        """The same road driven the other way round: same start point, centreline in the opposite order (so
        progress, laps and the sign of lateral offsets follow the new driving direction)."""
        points = self.centreline.points_m
        return dataclasses.replace(self, centreline=Centreline(np.concatenate([points[:1], points[:0:-1]])))

    @property
    def clockwise(self) -> bool:
        """Whether the driving direction is clockwise seen from above (negative signed area)."""
        return signed_area_m2(self.centreline.points_m) < 0


# -- names and loading -----------------------------------------------------------------------------------------------


def _data_dir() -> Path:
    return Path(str(resources.files("circuits") / "data"))


def user_circuits_dir() -> Path:
    """Where user circuits live: ``$DRIVEBENCH_CIRCUITS_DIR`` if set, else ``~/.local/share/drivebench/circuits``."""
    configured = CIRCUITS_DIR.value()
    if configured:
        return Path(configured).expanduser()
    return Path.home() / ".local" / "share" / "drivebench" / "circuits"


def builtin_circuit_names() -> list[str]:
    return sorted(path.stem for path in _data_dir().glob("*.yaml"))


def user_circuit_names() -> list[str]:
    """Plain-named ``*.yaml`` files in the user circuits folder (an absent folder has none)."""
    folder = user_circuits_dir()
    if not folder.is_dir():
        return []
    return sorted(path.stem for path in folder.glob("*.yaml") if PLAIN_NAME.fullmatch(path.stem))


def circuit_names() -> list[str]:
    """Every loadable circuit name but the generated ones (``random:SEED``, ``twisty:SEED``, ``grandprix:SEED``):
    built-ins and user circuits, sorted."""
    return sorted(set(builtin_circuit_names()) | set(user_circuit_names()))


def is_circuit_name(name: str) -> bool:
    """Whether :func:`load_circuit` knows ``name`` (without loading it): a built-in, a user circuit, random:SEED,
    twisty:SEED or grandprix:SEED."""
    return _generated_seed(name) is not None or name in circuit_names()


def _generated_prefix(name: str) -> str | None:
    return next((prefix for prefix in GENERATED_PREFIXES if name.startswith(prefix)), None)


def _generated_seed(name: str) -> int | None:
    prefix = _generated_prefix(name)
    if prefix is None:
        return None
    text = name[len(prefix) :]
    if not re.fullmatch(r"\d{1,18}", text):
        return None
    return int(text)


def load_circuit(name: str, *, direction: str = "forward") -> Circuit:
    """The circuit ``name``: a built-in, else a user circuit, else ``random:SEED``, ``twisty:SEED`` or
    ``grandprix:SEED``; ``direction="reverse"`` gives it driven the other way round (:meth:`Circuit.reversed`), as
    an episode spec's ``direction`` asks.

    :class:`CircuitError` names the known ones when it does not exist, and says what is wrong with a bad file.
    """
    if direction not in ("forward", "reverse"):
        raise CircuitError(f"direction must be forward or reverse, got {direction!r}")
    circuit = _load_forward(name)
    return circuit.reversed() if direction == "reverse" else circuit


def _load_forward(name: str) -> Circuit:
    builtin = _data_dir() / f"{name}.yaml"
    if PLAIN_NAME.fullmatch(name) and builtin.is_file():
        return circuit_from_file(builtin)
    if PLAIN_NAME.fullmatch(name):
        user = user_circuits_dir() / f"{name}.yaml"
        if user.is_file():
            return circuit_from_file(user, check=True)
    prefix = _generated_prefix(name)
    if prefix is not None:
        seed = _generated_seed(name)
        if seed is None:
            raise CircuitError(
                f"bad generated circuit name {name!r}: want {prefix}SEED with SEED a non-negative integer"
            )
        return GENERATORS[prefix](seed)
    close = difflib.get_close_matches(name, circuit_names(), n=1)  # protocol.suggest's rule; circuits/ is below it
    hint = f"; did you mean {close[0]!r}?" if close else ""
    raise CircuitError(f"unknown circuit {name!r} (known: {', '.join(circuit_names())}, or {GENERATED_NAMES}){hint}")


def circuit_from_file(path: Path, *, check: bool = False) -> Circuit:
    """The circuit in a YAML circuit file; ``check``: also run :func:`check_track` on its centreline."""
    try:
        raw = yaml.safe_load(path.read_text())
        spec = msgspec.convert(raw, CircuitFile)
    except (yaml.YAMLError, msgspec.ValidationError, OSError) as error:
        raise CircuitError(f"{path}: {error}") from None
    if len(spec.control_points_m) < 4:
        raise CircuitError(f"{path}: control_points_m needs at least 4 points, got {len(spec.control_points_m)}")
    points = np.asarray(spec.control_points_m, dtype=float)
    if not np.all(np.isfinite(points)):
        raise CircuitError(f"{path}: control_points_m must be finite numbers")
    for field in ("road_width_m", "line_width_m", "wall_height_m"):
        value = getattr(spec, field)
        if not (math.isfinite(value) and value > 0):
            raise CircuitError(f"{path}: {field} must be a positive number, got {value}")
    try:
        centreline = Centreline(closed_spline(points, step_m=RESAMPLE_STEP_M))
    except ValueError as error:
        raise CircuitError(f"{path}: {error}") from None
    if check:
        try:
            check_track(centreline.points_m, spec.road_width_m / 2)
        except CircuitError as error:
            raise CircuitError(f"{path}: {error}") from None
    return Circuit(
        name=spec.name,
        description=spec.description,
        source=spec.source,
        centreline=centreline,
        road_half_width_m=spec.road_width_m / 2,
        line_width_m=spec.line_width_m,
        wall_height_m=spec.wall_height_m,
    )


# -- geometry --------------------------------------------------------------------------------------------------------


def closed_spline(control_points_m: np.ndarray, *, step_m: float) -> np.ndarray:
    """A periodic cubic spline through the control points, resampled at (close to) ``step_m`` arc length."""
    from scipy.interpolate import splev, splprep  # lazy: see circuits/centreline.py

    closed = np.vstack([control_points_m, control_points_m[:1]])  # splprep(per=1) wants the loop closed
    tck, _ = splprep([closed[:, 0], closed[:, 1]], s=0, per=1)
    # Dense enough that the chord lengths measure the arc length well: 1000 samples per control point, capped for
    # long imported tracks (thousands of control points) at 400 k, i.e. still ~100 per 0.25 m on a 5 km lap.
    dense_count = min(50 * len(closed) * 20, max(400_000, 50 * 20 * 200))
    dense_u = np.linspace(0.0, 1.0, dense_count, endpoint=False)
    dense = np.stack(splev(dense_u, tck), axis=1)
    steps = np.hypot(*np.diff(np.vstack([dense, dense[:1]]), axis=0).T)
    s_dense = np.concatenate([[0.0], np.cumsum(steps)])
    length = s_dense[-1]
    count = max(8, round(length / step_m))
    s_target = np.linspace(0.0, length, count, endpoint=False)
    u_target = np.interp(s_target, s_dense, np.append(dense_u, 1.0))
    return np.stack(splev(u_target, tck), axis=1)


def resample_closed_polyline(points_m: np.ndarray, *, step_m: float) -> np.ndarray:
    """The closed polyline through ``points_m`` with vertices every (close to) ``step_m`` of arc length.

    Linear interpolation: the shape is that of the polyline, only the vertices move.
    """
    points = np.asarray(points_m, dtype=float)
    closed = np.vstack([points, points[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))])
    count = max(8, math.ceil(s[-1] / step_m))
    s_target = np.linspace(0.0, s[-1], count, endpoint=False)
    return np.column_stack([np.interp(s_target, s, closed[:, 0]), np.interp(s_target, s, closed[:, 1])])


def turn_radii_m(points_m: np.ndarray) -> np.ndarray:
    """Radius of the circle through each vertex and its two neighbours (closed polyline); inf where straight."""
    p = np.asarray(points_m, dtype=float)
    a = np.roll(p, 1, axis=0)
    c = np.roll(p, -1, axis=0)
    ab, bc, ca = np.hypot(*(p - a).T), np.hypot(*(c - p).T), np.hypot(*(a - c).T)
    twice_area = np.abs((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (p[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(twice_area > 0, ab * bc * ca / (2 * twice_area), np.inf)


def min_turn_radius_m(points_m: np.ndarray, *, step_m: float = CHECK_STEP_M) -> float:
    """The smallest turn radius of a closed centreline, measured on a copy resampled every ``step_m``."""
    return float(turn_radii_m(resample_closed_polyline(points_m, step_m=step_m)).min())


def signed_area_m2(points_m: np.ndarray) -> float:
    """Shoelace area of a closed polyline: > 0 anticlockwise, < 0 clockwise."""
    p = np.asarray(points_m, dtype=float)
    q = np.roll(p, -1, axis=0)
    return float(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]) / 2)


def find_crossing(points_m: np.ndarray) -> tuple[int, int, float, float] | None:
    """The first crossing of two non-adjacent segments of a closed polyline: (i, j, x, y) where segment i
    (points i -> i+1) crosses segment j > i, or None. Touching without crossing is not reported."""
    p = np.asarray(points_m, dtype=float)
    n = len(p)
    q = np.roll(p, -1, axis=0)
    lengths = np.hypot(*(q - p).T)
    midpoints = (p + q) / 2
    # Two crossing segments have midpoints within half the sum of their lengths of each other.
    from scipy.spatial import cKDTree

    pairs = cKDTree(midpoints).query_pairs(float(lengths.max()) * 1.0001 + 1e-9, output_type="ndarray")
    if len(pairs) == 0:
        return None
    i, j = pairs[:, 0], pairs[:, 1]
    keep = ((j - i) % n > 1) & ((i - j) % n > 1)
    i, j = i[keep], j[keep]

    def orient(o, a, b):
        return (a[:, 0] - o[:, 0]) * (b[:, 1] - o[:, 1]) - (a[:, 1] - o[:, 1]) * (b[:, 0] - o[:, 0])

    d1, d2 = orient(p[j], q[j], p[i]), orient(p[j], q[j], q[i])
    d3, d4 = orient(p[i], q[i], p[j]), orient(p[i], q[i], q[j])
    hits = np.flatnonzero((d1 * d2 < 0) & (d3 * d4 < 0))
    if hits.size == 0:
        return None
    order = np.lexsort((j[hits], i[hits]))
    k = hits[order[0]]
    t = d1[k] / (d1[k] - d2[k])
    x, y = p[i[k]] + t * (q[i[k]] - p[i[k]])
    a, b = sorted((int(i[k]), int(j[k])))
    return a, b, float(x), float(y)


def check_track(points_m: np.ndarray, road_half_width_m: float, *, min_gap_m: float | None = None) -> None:
    """Raise :class:`CircuitError` naming where, if a closed centreline cannot carry its road.

    Three tests, on a copy resampled every :data:`CHECK_STEP_M` (or finer for a small ``min_gap_m``):

    1. the centreline crosses itself: "the track crosses itself near (x, y)";
    2. two parts of it pass closer than ``min_gap_m``, centre to centre (default ``2 * road_half_width_m +``
       :data:`WALL_CLEARANCE_M`, i.e. their walls stay that far apart): "two parts of the track pass within
       d m near (x, y)". Two parts are *different* where the distance from a point to the rest of the track has a
       local minimum other than the point itself, so a bend, however tight, does not count; a hairpin does when
       its two legs run closer than the gap;
    3. it bends tighter than the road's half-width, folding the inner edge (and wall) over itself: "the track
       bends with a radius of r m (< half-width) near (x, y)".
    """
    points = np.asarray(points_m, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 3 or not np.all(np.isfinite(points)):
        raise CircuitError(f"a track needs at least 3 finite (x, y) points, got an array of shape {points.shape}")
    gap = 2 * road_half_width_m + WALL_CLEARANCE_M if min_gap_m is None else float(min_gap_m)
    step = min(CHECK_STEP_M, gap / 4) if gap > 0 else CHECK_STEP_M
    crossing = find_crossing(points)
    if crossing is not None:
        raise CircuitError(f"the track crosses itself near ({crossing[2]:.1f}, {crossing[3]:.1f})")
    resampled = resample_closed_polyline(points, step_m=step)
    close = _closest_other_part(resampled, gap)
    if close is not None:
        distance, x, y = close
        raise CircuitError(
            f"two parts of the track pass within {distance:.1f} m near ({x:.1f}, {y:.1f}) "
            f"(at least {gap:.1f} m needed, centre to centre)"
        )
    radii = turn_radii_m(resampled)
    k = int(np.argmin(radii))
    if radii[k] < road_half_width_m:
        x, y = resampled[k]
        raise CircuitError(
            f"the track bends with a radius of {radii[k]:.1f} m near ({x:.1f}, {y:.1f}), "
            f"tighter than the road's half-width {road_half_width_m:.2f} m"
        )


def _closest_other_part(points: np.ndarray, gap_m: float) -> tuple[float, float, float] | None:
    """(distance, x, y) of the closest pair of points on different parts of the track within gap_m, or None."""
    if gap_m <= 0:
        return None
    n = len(points)
    from scipy.spatial import cKDTree

    pairs = cKDTree(points).query_pairs(gap_m, output_type="ndarray")
    if len(pairs) == 0:
        return None
    pairs = np.vstack([pairs, pairs[:, ::-1]])  # local minimum of the distance from i, over j
    i, j = pairs[:, 0], pairs[:, 1]
    keep = ((j - i) % n > 1) & ((i - j) % n > 1)
    i, j = i[keep], j[keep]

    def dist(a, b):
        return np.hypot(*(points[a] - points[b]).T)

    d = dist(i, j)
    local_min = (d <= dist(i, (j - 1) % n)) & (d <= dist(i, (j + 1) % n))
    if not np.any(local_min):
        return None
    k = np.flatnonzero(local_min)[np.argmin(d[local_min])]
    x, y = (points[i[k]] + points[j[k]]) / 2
    return float(d[k]), float(x), float(y)
