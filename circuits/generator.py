"""Procedural circuits: ``random_circuit(seed)``, ``twisty_circuit(seed)`` and ``grandprix_circuit(seed)``, loaded
by name as ``random:SEED``, ``twisty:SEED`` and ``grandprix:SEED``.

**random:SEED.**
A candidate is a periodic cubic spline through 7-14 control points scattered around a circle: the points are
taken in clockwise order at evenly spaced angles with a random jitter, at random distances from the centre (so the
circle becomes bays, bulges, S-bends and the odd hairpin). A candidate is kept when

* its lap is 400-1500 m,
* it never turns tighter than :data:`MIN_RADIUS_M`,
* :func:`~circuits.library.check_track` passes with a :data:`MIN_GAP_M` centre-to-centre clearance (no
  crossing, and the walls of two parts of the track never come close),

otherwise the next candidate is drawn from a seed derived from ``(seed, attempt)``. Everything is drawn from
NumPy's PCG64 generator seeded by ``[seed, attempt]``, so a seed always gives the same circuit. The start is moved
to the straightest stretch of the lap (the point whose surroundings, :data:`START_WINDOW_M` either way, bend least).
Road, line and walls are at Behavior Metrics' scale (3 m, 0.10 m, 0.5 m).

**twisty:SEED.** The spline circuits bend gently: at most 2 % of their lap turns tighter than 10 m (seeds 300-700),
against 12 % of Montmelo's. A twisty circuit is built the way real circuits are drawn, straights and arcs: a
polygon of 7-11 corners scattered around a circle (deeper bays than the spline's), each corner rounded by an arc of
radius 8.5-12 m tangent to both sides (rejected when two arcs do not fit on one side with a 4 m straight between).
A typical one turns tighter than 15 m over a sixth of its lap (Montmelo: a fifth). The same checks and start
rule as random:SEED apply.

**grandprix:SEED.** Neither family has a real circuit's layout: over seeds 0-29 no random or twisty lap has two
straights of 120 m (twisty's longest straight is 127 m, random's 50 m) nor a hairpin that turns more than 150
degrees (``tests/test_circuits.py``). A grand prix circuit is drawn as a real one is, straights and corners: a
long main straight (120-300 m) braking into a hairpin (radius 8.25-9.75 m, turning 160-180 degrees), then medium
corners (4-9 of them over seeds 0-199; radius 14-40 m, one or two of them left-handers) with a chicane among them
(a left-right or right-left pair of 30-60 degree bends of radius 8.5-12 m, 3-10 m of straight between), a short
straight (12-70 m) into each corner, and a second long straight: the one heading most nearly back along the main
straight. The corners turn one round clockwise; the straights are then stretched, each in proportion to its
length, just enough to close the lap, and the candidate is kept when the long straights stay 120-300 m and none
is under 6 m. The lap is 600-1500 m; the same checks (:data:`MIN_RADIUS_M`, :data:`MIN_GAP_M`, ``check_track``),
start rule and resampling of candidates as random:SEED apply.
"""

from __future__ import annotations

import math

import numpy as np

from circuits.centreline import Centreline
from circuits.library import (
    GENERATORS,
    GRANDPRIX_PREFIX,
    RANDOM_PREFIX,
    RESAMPLE_STEP_M,
    TWISTY_PREFIX,
    Circuit,
    CircuitError,
    check_track,
    closed_spline,
    min_turn_radius_m,
    resample_closed_polyline,
    signed_area_m2,
    turn_radii_m,
)

ROAD_WIDTH_M = 3.0
LINE_WIDTH_M = 0.10
WALL_HEIGHT_M = 0.5
MIN_LENGTH_M = 400.0
MAX_LENGTH_M = 1500.0
MIN_RADIUS_M = 8.0
MIN_GAP_M = 8.0
START_WINDOW_M = 15.0
MAX_ATTEMPTS = 200
TWISTY_FILLET_RADII_M = (8.5, 12.0)
TWISTY_MIN_STRAIGHT_M = 4.0
ARC_STEP_M = 0.05
GRANDPRIX_LENGTHS_M = (600.0, 1500.0)
GRANDPRIX_RIGHT_MEAN_TURN_DEG = (45.0, 90.0)  # sets how many right-hand medium corners share their turning
GRANDPRIX_LONG_STRAIGHT_M = (120.0, 300.0)
GRANDPRIX_SHORT_STRAIGHT_M = (12.0, 70.0)
GRANDPRIX_MIN_STRAIGHT_M = 6.0
# Not under MIN_RADIUS_M: arcs sampled every ARC_STEP_M measure a hair tighter than drawn.
GRANDPRIX_HAIRPIN_RADII_M = (8.25, 9.75)
GRANDPRIX_HAIRPIN_TURN_DEG = (160.0, 180.0)
GRANDPRIX_CHICANE_RADII_M = (8.5, 12.0)
GRANDPRIX_CHICANE_TURN_DEG = (30.0, 60.0)
GRANDPRIX_CHICANE_STRAIGHT_M = (3.0, 10.0)
GRANDPRIX_CORNER_RADII_M = (14.0, 40.0)
GRANDPRIX_CORNER_TURN_DEG = (25.0, 130.0)
GRANDPRIX_LEFT_TURN_DEG = (30.0, 80.0)

# A piece of a grand prix lap: (length_m, turn_rad); a straight where turn_rad is 0, else an arc of radius
# length_m / |turn_rad| turning left where turn_rad > 0.
Piece = tuple[float, float]


def random_circuit(seed: int) -> Circuit:
    """The procedural spline circuit of ``seed`` (a non-negative integer), named ``random:SEED``; see the module doc."""
    return _generate(seed, prefix=RANDOM_PREFIX, candidate=_candidate, kind="procedural circuit")


def twisty_circuit(seed: int) -> Circuit:
    """The procedural straights-and-arcs circuit of ``seed``, named ``twisty:SEED``; see the module doc."""
    return _generate(seed, prefix=TWISTY_PREFIX, candidate=_twisty_candidate, kind="twisty procedural circuit")


def grandprix_circuit(seed: int) -> Circuit:
    """The procedural Grand-Prix-like circuit of ``seed`` (long straights, a hairpin, a chicane), named
    ``grandprix:SEED``; see the module doc."""
    return _generate(
        seed, prefix=GRANDPRIX_PREFIX, candidate=_grandprix_candidate, kind="grand prix procedural circuit"
    )


def _generate(seed: int, *, prefix: str, candidate, kind: str) -> Circuit:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CircuitError(f"a {prefix[:-1]} circuit's seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, attempt])
        points = candidate(rng)
        if points is not None:
            return Circuit(
                name=f"{prefix}{seed}",
                description=f"{kind} of seed {seed} (candidate {attempt})",
                source="drivebench procedural generator (circuits.generator)",
                centreline=Centreline(points),
                road_half_width_m=ROAD_WIDTH_M / 2,
                line_width_m=LINE_WIDTH_M,
                wall_height_m=WALL_HEIGHT_M,
            )
    raise CircuitError(f"no valid {prefix[:-1]} circuit for seed {seed} in {MAX_ATTEMPTS} attempts")  # pragma: no cover


def _candidate(rng: np.random.Generator) -> np.ndarray | None:
    """A clockwise spline centreline resampled every RESAMPLE_STEP_M, starting on its straightest stretch; None if
    the draw fails a test."""
    count = int(rng.integers(7, 15))
    target_length = rng.uniform(450.0, 1350.0)
    # Scattered radii make the lap longer than the circle's circumference; 1.15 is the typical ratio.
    mean_radius = target_length / (2 * math.pi * 1.15)
    control = _scattered_polygon(rng, count=count, mean_radius_m=mean_radius, scatter=(0.55, 1.25))
    return _checked_and_started(closed_spline(control, step_m=RESAMPLE_STEP_M))


def _twisty_candidate(rng: np.random.Generator) -> np.ndarray | None:
    """A clockwise straights-and-arcs centreline (a scattered polygon with rounded corners), like _candidate's."""
    count = int(rng.integers(7, 12))
    target_length = rng.uniform(450.0, 1100.0)
    corners = _scattered_polygon(
        rng, count=count, mean_radius_m=target_length / (2 * math.pi * 1.2), scatter=(0.3, 1.3)
    )
    dense = _rounded_polygon(corners, fillet_radii_m=rng.uniform(*TWISTY_FILLET_RADII_M, count))
    if dense is None:
        return None
    return _checked_and_started(resample_closed_polyline(dense, step_m=RESAMPLE_STEP_M))


def _scattered_polygon(
    rng: np.random.Generator, *, count: int, mean_radius_m: float, scatter: tuple[float, float]
) -> np.ndarray:
    """``count`` points in clockwise order at evenly spaced, jittered angles, at scattered distances from the centre."""
    spacing = 2 * math.pi / count
    angles = -spacing * np.arange(count) + rng.uniform(-0.3, 0.3, count) * spacing  # clockwise
    radii = mean_radius_m * rng.uniform(*scatter, count)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def _rounded_polygon(corners_m: np.ndarray, *, fillet_radii_m: np.ndarray) -> np.ndarray | None:
    """The closed polygon with each corner replaced by an arc of its radius tangent to both sides, sampled every
    ARC_STEP_M along the arcs (the straights are the gaps between arcs); None where two arcs do not fit on one side
    with TWISTY_MIN_STRAIGHT_M between them."""
    sides = np.roll(corners_m, -1, axis=0) - corners_m  # side i runs from corner i to corner i + 1
    side_lengths = np.hypot(*sides.T)
    heading_out = sides / side_lengths[:, None]
    heading_in = np.roll(heading_out, 1, axis=0)
    cross = heading_in[:, 0] * heading_out[:, 1] - heading_in[:, 1] * heading_out[:, 0]
    turn_rad = np.arctan2(cross, np.sum(heading_in * heading_out, axis=1))  # > 0: a left turn
    tangent_m = fillet_radii_m * np.tan(np.abs(turn_rad) / 2)  # corner to where the arc meets each side
    if np.any(tangent_m + np.roll(tangent_m, -1) + TWISTY_MIN_STRAIGHT_M > side_lengths):
        return None
    arcs = []
    for corner, heading, turn, radius, tangent in zip(corners_m, heading_in, turn_rad, fillet_radii_m, tangent_m):
        arc_start = corner - heading * tangent
        left_normal = np.array([-heading[1], heading[0]])
        centre = arc_start + math.copysign(radius, turn) * left_normal
        start_angle = math.atan2(arc_start[1] - centre[1], arc_start[0] - centre[0])
        count = max(2, int(abs(turn) * radius / ARC_STEP_M))
        angles = start_angle + turn * np.arange(count + 1) / count
        arcs.append(centre + radius * np.column_stack([np.cos(angles), np.sin(angles)]))
    return np.vstack(arcs)


def _grandprix_candidate(rng: np.random.Generator) -> np.ndarray | None:
    """A clockwise Grand-Prix-like centreline (straights and the corners of :func:`_grandprix_corners`, the straights
    stretched to close the lap), like _candidate's."""
    corners = _grandprix_corners(rng)
    if corners is None:
        return None
    count = len(corners)
    # Straight i leads into corner i. Straight 0 (the main straight, into the hairpin: a real circuit's braking
    # zone) and the straight that runs most nearly back the other way are the long ones, so that they close most
    # of the lap between them and the short straights need not stretch far. Not straight 1, out of the hairpin:
    # two long straights joined by the hairpin would make every lap one long finger.
    headings_rad = _straight_headings_rad(corners)
    long_index = 2 + int(np.argmin(np.abs(np.remainder(headings_rad[2:], 2 * math.pi) - math.pi)))
    long = np.zeros(count, dtype=bool)
    long[[0, long_index]] = True
    straights_m = rng.uniform(*GRANDPRIX_SHORT_STRAIGHT_M, count)
    straights_m[long] = rng.uniform(*GRANDPRIX_LONG_STRAIGHT_M, 2)
    closed_m = _closing_straights(corners, straights_m)
    if np.any(closed_m[long] < GRANDPRIX_LONG_STRAIGHT_M[0]) or np.any(closed_m > GRANDPRIX_LONG_STRAIGHT_M[1]):
        return None
    if np.any(closed_m < GRANDPRIX_MIN_STRAIGHT_M):
        return None
    pieces = [piece for straight_m, corner in zip(closed_m, corners) for piece in [(straight_m, 0.0), *corner]]
    dense = _trace(pieces)[:-1]  # the last point closes the lap onto the first
    return _checked_and_started(resample_closed_polyline(dense, step_m=RESAMPLE_STEP_M), lengths_m=GRANDPRIX_LENGTHS_M)


def _grandprix_corners(rng: np.random.Generator) -> list[list[Piece]] | None:
    """The corners of a lap in driving order, each a list of arcs (the chicane's with a short straight between):
    the hairpin first, then medium corners (one or two of them left-handers) with the chicane among them; together
    they turn one clockwise round. None where a medium corner would turn too little or too much."""
    hairpin_rad = math.radians(rng.uniform(*GRANDPRIX_HAIRPIN_TURN_DEG))
    lefts_rad = np.radians(rng.uniform(*GRANDPRIX_LEFT_TURN_DEG, int(rng.integers(1, 3))))
    rights_total_rad = 2 * math.pi - hairpin_rad + lefts_rad.sum()
    rights_count = max(2, round(rights_total_rad / math.radians(rng.uniform(*GRANDPRIX_RIGHT_MEAN_TURN_DEG))))
    shares = rng.uniform(0.5, 1.5, rights_count)
    rights_rad = rights_total_rad * shares / shares.sum()
    low, high = np.radians(GRANDPRIX_CORNER_TURN_DEG)
    if np.any(rights_rad < low) or np.any(rights_rad > high):
        return None
    turns_rad = rng.permutation(np.concatenate([-rights_rad, lefts_rad]))
    mediums: list[list[Piece]] = [[_arc(rng.uniform(*GRANDPRIX_CORNER_RADII_M), turn)] for turn in turns_rad]
    hairpin = [_arc(rng.uniform(*GRANDPRIX_HAIRPIN_RADII_M), -hairpin_rad)]
    chicane_rad = math.radians(rng.uniform(*GRANDPRIX_CHICANE_TURN_DEG)) * rng.choice([-1.0, 1.0])
    chicane = [
        _arc(rng.uniform(*GRANDPRIX_CHICANE_RADII_M), chicane_rad),
        (rng.uniform(*GRANDPRIX_CHICANE_STRAIGHT_M), 0.0),
        _arc(rng.uniform(*GRANDPRIX_CHICANE_RADII_M), -chicane_rad),
    ]
    mediums.insert(int(rng.integers(0, len(mediums) + 1)), chicane)
    return [hairpin, *mediums]


def _straight_headings_rad(corners: list[list[Piece]]) -> np.ndarray:
    """The heading of each straight (straight i leads into corner i), straight 0 running along x."""
    return np.concatenate([[0.0], np.cumsum([sum(turn for _, turn in corner) for corner in corners])[:-1]])


def _arc(radius_m: float, turn_rad: float) -> Piece:
    return (radius_m * abs(turn_rad), turn_rad)


def _closing_straights(corners: list[list[Piece]], straights_m: np.ndarray) -> np.ndarray:
    """``straights_m`` (straight i leads into corner i) changed as little as closes the lap: each in proportion to
    its length, so the long straights take most of it."""
    open_end = _trace([piece for corner in corners for piece in [(0.0, 0.0), *corner]])[-1]
    headings_rad = _straight_headings_rad(corners)
    directions = np.stack([np.cos(headings_rad), np.sin(headings_rad)])  # 2 x straights
    gap_m = open_end + directions @ straights_m
    weighted = directions * straights_m
    # Solvable: the straights turn a full round between them, so they never all run along one line.
    return straights_m + weighted.T @ np.linalg.solve(weighted @ directions.T, -gap_m)


def _trace(pieces: list[Piece]) -> np.ndarray:
    """The points a turtle passes driving ``pieces`` from the origin along x: every straight's ends, and the arcs
    sampled every ARC_STEP_M."""
    position, heading = np.zeros(2), 0.0
    points = [position]
    for length_m, turn_rad in pieces:
        if turn_rad == 0.0:
            position = position + length_m * np.array([math.cos(heading), math.sin(heading)])
            points.append(position)
            continue
        radius_m = length_m / abs(turn_rad)
        start_rad = heading - math.copysign(math.pi / 2, turn_rad)  # the position seen from the arc's centre
        centre = position - radius_m * np.array([math.cos(start_rad), math.sin(start_rad)])
        count = max(2, math.ceil(length_m / ARC_STEP_M))
        angles = start_rad + turn_rad * np.arange(1, count + 1) / count
        arc = centre + radius_m * np.column_stack([np.cos(angles), np.sin(angles)])
        points.extend(arc)
        position, heading = arc[-1], heading + turn_rad
    return np.array(points)


def _checked_and_started(
    points: np.ndarray, *, lengths_m: tuple[float, float] = (MIN_LENGTH_M, MAX_LENGTH_M)
) -> np.ndarray | None:
    """``points`` rolled to start on their straightest stretch, or None if the lap fails a test of the module doc."""
    length = float(np.sum(np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)))
    if not lengths_m[0] <= length <= lengths_m[1] or signed_area_m2(points) >= 0:
        return None
    if min_turn_radius_m(points) < MIN_RADIUS_M:
        return None
    try:
        check_track(points, ROAD_WIDTH_M / 2, min_gap_m=MIN_GAP_M)
    except CircuitError:
        return None
    curvature = 1.0 / turn_radii_m(points)
    window = 2 * round(START_WINDOW_M / RESAMPLE_STEP_M) + 1
    from scipy.ndimage import maximum_filter1d  # lazy: see circuits/centreline.py

    worst_nearby = maximum_filter1d(curvature, size=window, mode="wrap")
    start = int(np.argmin(worst_nearby))
    return np.roll(points, -start, axis=0)


GENERATORS.update({RANDOM_PREFIX: random_circuit, TWISTY_PREFIX: twisty_circuit, GRANDPRIX_PREFIX: grandprix_circuit})
