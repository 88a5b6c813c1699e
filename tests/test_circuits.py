"""Circuit geometry: built-in and random circuits are closed and sane; check_track finds crossings and close
passes; user circuits are found by name; pictures; projection is exact and keeps to its branch."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from circuits import Centreline, Circuit, CircuitError, circuit_names, load_circuit
from circuits.generator import grandprix_circuit, random_circuit, twisty_circuit
from circuits.library import (
    GENERATORS,
    builtin_circuit_names,
    check_track,
    min_turn_radius_m,
    resample_closed_polyline,
    signed_area_m2,
    turn_radii_m,
    user_circuits_dir,
)
from circuits.picture import ROAD_RGB, circuit_picture, save_circuit_picture

# name: (lap length range m, bounding box (x, y) m or None); sizes after Behavior Metrics' circuits.
BUILTIN_SIZES = {
    "simple": ((430, 460), (107, 104)),
    "many_curves": ((770, 820), None),
    "montmelo": ((720, 760), (216, 63)),
    "montreal": ((1400, 1470), (617, 227)),
    "nurburgring": ((540, 570), (188, 91)),
    "monaco": ((800, 1000), None),
    "extended_simple": ((600, 700), None),
}


def brute_force(centreline: Centreline, x: float, y: float) -> tuple[float, float]:
    """(distance, s) of the closest point over every segment."""
    p = centreline.points_m
    v = np.roll(p, -1, axis=0) - p
    t = np.clip(((x - p[:, 0]) * v[:, 0] + (y - p[:, 1]) * v[:, 1]) / (v**2).sum(axis=1), 0, 1)
    d = np.hypot(x - (p[:, 0] + t * v[:, 0]), y - (p[:, 1] + t * v[:, 1]))
    i = int(np.argmin(d))
    return float(d[i]), float(centreline.s_m[i] + t[i] * np.hypot(*v[i]))


def segments_cross(a, b, c, d) -> bool:
    def orient(p, q, r):
        return np.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))

    return orient(a, b, c) != orient(a, b, d) and orient(c, d, a) != orient(c, d, b)


@pytest.fixture(autouse=True)
def _no_user_circuits(tmp_path, monkeypatch):
    """Never read or write the real user circuits folder."""
    monkeypatch.setenv("DRIVEBENCH_CIRCUITS_DIR", str(tmp_path / "user-circuits"))


def test_the_builtin_circuits_are_the_behavior_metrics_set():
    assert set(builtin_circuit_names()) == set(BUILTIN_SIZES)


@pytest.mark.parametrize("name", builtin_circuit_names())
def test_builtin_circuit_is_closed_simple_and_at_behavior_metrics_scale(name):
    circuit = load_circuit(name)
    points = circuit.centreline.points_m
    steps = np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)
    assert steps.max() < 0.3 and steps.min() > 0.2  # resampled at ~0.25 m, closing gap included
    assert 400 < circuit.length_m < 1600
    assert circuit.road_half_width_m == pytest.approx(1.5)
    # Not self-intersecting: no two non-adjacent segments of a coarse copy cross.
    coarse = points[::8]
    n = len(coarse)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            assert not segments_cross(coarse[i], coarse[(i + 1) % n], coarse[j], coarse[(j + 1) % n]), (i, j)
    x, y, yaw = circuit.start_pose()
    assert (x, y) == tuple(points[0]) and -math.pi <= yaw <= math.pi


@pytest.mark.parametrize("name", builtin_circuit_names())
def test_builtin_circuit_size_shape_and_clearance(name):
    circuit = load_circuit(name)
    points = circuit.centreline.points_m
    (low, high), box = BUILTIN_SIZES[name]
    assert low < circuit.length_m < high
    if box is not None:
        extent = np.ptp(points, axis=0)
        assert extent == pytest.approx(box, rel=0.12)
    # Walls never overlap: no two parts of the track within 8 m, centre to centre; no bend under 6 m radius.
    check_track(points, circuit.road_half_width_m, min_gap_m=8.0)
    assert min_turn_radius_m(points) >= 6.0
    assert signed_area_m2(points) < 0  # clockwise
    assert circuit.line_width_m == pytest.approx(0.10) and circuit.wall_height_m == pytest.approx(0.5)
    # The start is on the centreline, on a straight: nothing within 10 m of it bends tighter than 25 m.
    x, y, yaw = circuit.start_pose()
    assert abs(circuit.centreline.project(x, y).lateral_m) < 1e-9
    s = circuit.centreline.s_m
    near_start = (s < 10.0) | (s > circuit.length_m - 10.0)
    assert turn_radii_m(points)[near_start].min() > 25.0


def test_simple_circuit_size_matches_behavior_metrics():
    circuit = load_circuit("simple")
    assert 430 < circuit.length_m < 460
    extent = np.ptp(circuit.centreline.points_m, axis=0)
    assert 100 < extent[0] < 120 and 100 < extent[1] < 120


def test_projection_matches_brute_force_and_tracking():
    centreline = load_circuit("simple").centreline
    rng = np.random.default_rng(0)
    s_prev = None
    for s in np.linspace(0, centreline.length_m, 400, endpoint=False):
        x, y, heading = centreline.pose_at(s)
        offset = rng.uniform(-1.4, 1.4)
        px, py = x - offset * math.sin(heading), y + offset * math.cos(heading)
        for near in (None, s_prev):
            projection = centreline.project(px, py, near_s_m=near)
            distance, _ = brute_force(centreline, px, py)
            assert abs(projection.lateral_m) == pytest.approx(distance, abs=1e-9)
        assert projection.lateral_m == pytest.approx(offset, abs=0.05)  # + is left
        s_prev = projection.s_m


@pytest.mark.parametrize("name", ["simple", "montmelo", "twisty:10"])
def test_many_points_at_once_project_as_one_at_a_time(name):
    """project_many (the report's colours and progress) is project()'s global search, vectorised: the same arc
    length and signed distance, and the brute-force distance."""
    centreline = load_circuit(name).centreline
    rng = np.random.default_rng(1)
    points = np.array([centreline.pose_at(s)[:2] for s in rng.uniform(0, centreline.length_m, 300)])
    points += rng.normal(0.0, 1.0, points.shape)
    s_m, offsets = centreline.project_many(points[:, 0], points[:, 1])
    one_at_a_time = [centreline.project(x, y) for x, y in points]
    np.testing.assert_allclose(offsets, [p.lateral_m for p in one_at_a_time], atol=1e-9)
    np.testing.assert_allclose(s_m, [p.s_m for p in one_at_a_time], atol=1e-9)
    np.testing.assert_allclose(np.abs(offsets), [brute_force(centreline, x, y)[0] for x, y in points], atol=1e-9)
    assert all(part.shape == (0,) for part in centreline.project_many(np.zeros(0), np.zeros(0)))


def test_tracking_keeps_to_its_own_branch_where_two_run_close():
    # A hairpin: two straights 2.5 m apart, joined by half circles.
    half = np.linspace(-np.pi / 2, np.pi / 2, 40, endpoint=False)
    top = np.column_stack([np.linspace(0, 100, 400, endpoint=False), np.zeros(400)])
    right = np.column_stack([100 + 1.25 * np.cos(half), 1.25 + 1.25 * np.sin(half)])
    bottom = np.column_stack([np.linspace(100, 0, 400, endpoint=False), np.full(400, 2.5)])
    left = np.column_stack([-1.25 * np.cos(half), 1.25 - 1.25 * np.sin(half)])
    centreline = Centreline(np.vstack([top, right, bottom, left]))
    start = centreline.project(10.0, 0.0)
    # 1.4 m left of the first straight: nearer the other straight (1.1 m), but the car is still on its own.
    tracked = centreline.project(10.5, 1.4, near_s_m=start.s_m)
    assert tracked.lateral_m == pytest.approx(1.4)
    assert centreline.project(10.5, 1.4).lateral_m == pytest.approx(1.1)  # the global answer is the other branch


def test_unknown_circuit_names_the_known_ones():
    with pytest.raises(CircuitError, match=r"unknown circuit 'monza' \(known: .*simple"):
        load_circuit("monza")


def test_bad_centrelines_are_rejected():
    with pytest.raises(ValueError, match="N >= 3"):
        Centreline(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="finite"):
        Centreline(np.array([[0, 0], [1, np.nan], [2, 0]]))
    with pytest.raises(ValueError, match="repeated"):
        Centreline(np.array([[0, 0], [0, 0], [1, 1]]))


# -- check_track ------------------------------------------------------------------------------------------------------


def circle(radius: float, count: int = 400, centre=(0.0, 0.0)) -> np.ndarray:
    t = -np.linspace(0, 2 * np.pi, count, endpoint=False)  # clockwise
    return np.column_stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)])


def stadium(length: float, gap: float, step: float = 0.5) -> np.ndarray:
    """Two straights ``gap`` apart joined by half circles, clockwise."""
    r = gap / 2
    straight = np.arange(0, length, step)
    arc = np.linspace(np.pi / 2, -np.pi / 2, max(8, int(np.pi * r / step)), endpoint=False)
    return np.vstack(
        [
            np.column_stack([straight, np.full_like(straight, gap)]),
            np.column_stack([length + r * np.cos(arc), r + r * np.sin(arc)]),
            np.column_stack([length - straight, np.zeros_like(straight)]),
            np.column_stack([-r * np.cos(arc), r - r * np.sin(arc)]),
        ]
    )


def test_check_track_accepts_a_circle_and_a_wide_stadium():
    assert check_track(circle(30.0), 1.5, min_gap_m=8.0) is None
    assert check_track(stadium(100.0, 20.0), 1.5, min_gap_m=8.0) is None


def test_check_track_finds_a_crossing():
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    eight = np.column_stack([100 * np.sin(t), 50 * np.sin(2 * t)]) + [10.0, 20.0]
    with pytest.raises(CircuitError, match=r"the track crosses itself near \(10\.0, 20\.0\)"):
        check_track(eight, 1.5)


def test_check_track_finds_two_parts_passing_close():
    # A 7 m wide hairpin (R 3.5 m > the 1.5 m half-width): its legs run 7 m apart, under an 8 m clearance...
    with pytest.raises(CircuitError, match=r"two parts of the track pass within 7\.0 m near \(\d+\.\d, 3\.5\)"):
        check_track(stadium(100.0, 7.0), 1.5, min_gap_m=8.0)
    # ... but their walls (3 m road) are 4 m apart, enough for the default clearance (2 * 1.5 + 0.5 m).
    check_track(stadium(100.0, 7.0), 1.5)
    with pytest.raises(CircuitError, match="two parts of the track pass within"):
        check_track(stadium(100.0, 3.2), 1.5)


def test_a_tight_bend_is_not_two_parts_of_the_track_but_may_fold_the_road():
    check_track(circle(4.5, 200), 1.5, min_gap_m=8.0)  # one part: a bend, however tight, is no close pass
    with pytest.raises(CircuitError, match=r"bends with a radius of 4\.5 m near .* half-width 5\.00 m"):
        check_track(circle(4.5, 200), 5.0, min_gap_m=0.0)


def test_check_track_rejects_malformed_points():
    with pytest.raises(CircuitError, match="at least 3 finite"):
        check_track(np.array([[0.0, 0.0], [1.0, np.nan], [2.0, 0.0]]), 1.5)


# -- random circuits --------------------------------------------------------------------------------------------------

GENERATED_SEEDS = (
    [("random:", seed) for seed in range(20)]
    + [("twisty:", seed) for seed in range(10)]
    + [("grandprix:", seed) for seed in range(30)]  # every one of 30 seeds builds (MAX_ATTEMPTS candidates at most)
)


@pytest.mark.parametrize("prefix, seed", GENERATED_SEEDS)
def test_generated_circuits_are_valid_and_deterministic(prefix, seed):
    circuit = GENERATORS[prefix](seed)
    again = load_circuit(f"{prefix}{seed}")
    assert circuit.name == again.name == f"{prefix}{seed}"
    np.testing.assert_array_equal(circuit.centreline.points_m, again.centreline.points_m)
    points = circuit.centreline.points_m
    steps = np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)
    assert steps.max() < 0.3 and steps.min() > 0.2  # closed, ~0.25 m spacing
    assert 400 <= circuit.length_m <= 1500
    assert circuit.road_half_width_m == pytest.approx(1.5)
    assert signed_area_m2(points) < 0
    assert min_turn_radius_m(points) >= 8.0 - 1e-9
    check_track(points, 1.5, min_gap_m=8.0)


def test_random_circuits_differ_by_seed():
    assert random_circuit(1).length_m != random_circuit(2).length_m
    assert twisty_circuit(1).length_m != twisty_circuit(2).length_m
    assert grandprix_circuit(1).length_m != grandprix_circuit(2).length_m


def _tight_fraction(circuit) -> float:
    return float(np.mean(turn_radii_m(circuit.centreline.points_m) < 15.0))


def test_twisty_circuits_turn_tight_as_montmelo_does():
    """What twisty:SEED is for: hairpins. Over seeds 0-9 its laps turn tighter than 15 m about as often as
    Montmelo's (a fifth of the lap) and far more often than the spline circuits'."""
    twisty = np.mean([_tight_fraction(twisty_circuit(seed)) for seed in range(10)])
    spline = np.mean([_tight_fraction(random_circuit(seed)) for seed in range(10)])
    assert twisty > 0.5 * _tight_fraction(load_circuit("montmelo"))
    assert twisty > 5 * spline


@dataclass(frozen=True)
class Bend:
    """A stretch of a lap tighter than BEND_RADIUS_M: where it starts and ends (indices, end exclusive, may pass the
    lap's end), its signed turn (> 0 left) and its smallest radius."""

    start: int
    end: int
    turn_rad: float
    min_radius_m: float


STRAIGHT_RADIUS_M = 1000.0  # a stretch that bends less than this is a straight (arcs here are 40 m at most)
BEND_RADIUS_M = 15.0


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of each maximal run of True in a cyclic mask; end is exclusive and may exceed len(mask)."""
    if mask.all():
        return [(0, len(mask))]
    shift = int(np.argmin(mask))  # a False: no run wraps past it
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.roll(mask, -shift).astype(int), [0]])))
    return [(int(a) + shift, int(b) + shift) for a, b in zip(edges[::2], edges[1::2])]


def _layout(circuit) -> tuple[list[float], list[Bend], float]:
    """The lap's straights (m), its bends, and the spacing (m) of the points they index."""
    points = resample_closed_polyline(circuit.centreline.points_m, step_m=0.5)
    step_m = circuit.length_m / len(points)
    radii = turn_radii_m(points)
    sides = np.roll(points, -1, axis=0) - points
    headings = np.arctan2(sides[:, 1], sides[:, 0])
    turns = np.remainder(headings - np.roll(headings, 1) + np.pi, 2 * np.pi) - np.pi  # the turn at each point
    straights = [(end - start) * step_m for start, end in _runs(radii > STRAIGHT_RADIUS_M)]
    bends = []
    for start, end in _runs(radii < BEND_RADIUS_M):
        at = np.arange(start, end) % len(points)
        bends.append(Bend(start, end, float(turns[at].sum()), float(radii[at].min())))
    return straights, bends, step_m


def _long_straights(circuit) -> int:
    return sum(length >= 120.0 for length in _layout(circuit)[0])


def _hairpins(circuit) -> list[Bend]:
    """Bends tighter than 10 m that turn more than 150 degrees."""
    return [b for b in _layout(circuit)[1] if b.min_radius_m < 10.0 and abs(b.turn_rad) > math.radians(150)]


def _chicanes(circuit) -> int:
    """Pairs of consecutive bends that turn opposite ways, each more than 20 degrees, at most 15 m apart."""
    _, bends, step_m = _layout(circuit)
    count = 0
    for first, second in zip(bends, bends[1:] + bends[:1]):
        gap_m = ((second.start - first.end) % round(circuit.length_m / step_m)) * step_m
        turns_rad = (first.turn_rad, second.turn_rad)
        if turns_rad[0] * turns_rad[1] < 0 and min(map(abs, turns_rad)) > math.radians(20) and gap_m <= 15.0:
            count += 1
    return count


@pytest.mark.parametrize("seed", range(30))
def test_grandprix_circuits_have_long_straights_a_hairpin_and_a_chicane(seed):
    """What grandprix:SEED is for: a real circuit's layout at Behavior Metrics' scale."""
    circuit = grandprix_circuit(seed)
    assert 600.0 <= circuit.length_m <= 1500.0
    assert _long_straights(circuit) >= 2
    hairpins = _hairpins(circuit)
    assert hairpins and all(hairpin.min_radius_m >= 8.0 - 1e-6 for hairpin in hairpins)
    assert _chicanes(circuit) >= 1
    # The start rule put the start on a straight: nothing within 15 m of it bends.
    s = circuit.centreline.s_m
    near_start = (s < 15.0) | (s > circuit.length_m - 15.0)
    assert turn_radii_m(circuit.centreline.points_m)[near_start].min() > STRAIGHT_RADIUS_M


@pytest.mark.parametrize("generator", [random_circuit, twisty_circuit])
def test_the_other_families_lack_the_grandprix_layout(generator):
    """Over seeds 0-29 no random or twisty lap has two straights of 120 m or a hairpin of over 150 degrees, which
    every grandprix lap has: the family is a layout the training recipes (random: and twisty:) never drove."""
    circuits = [generator(seed) for seed in range(30)]
    assert [c.name for c in circuits if _long_straights(c) >= 2] == []
    assert [c.name for c in circuits if _hairpins(c)] == []


@pytest.mark.parametrize(
    "name", ["random:", "random:-1", "random:x", "random:1.5", "twisty:", "twisty:x", "grandprix:", "grandprix:-3"]
)
def test_bad_generated_names_are_refused(name):
    with pytest.raises(CircuitError, match=f"{name.split(':')[0]}:SEED"):
        load_circuit(name)


@pytest.mark.parametrize("generator", [random_circuit, twisty_circuit, grandprix_circuit])
def test_generated_circuit_wants_a_non_negative_integer(generator):
    with pytest.raises(CircuitError, match="non-negative integer"):
        generator(-1)


# -- user circuits --------------------------------------------------------------------------------------------------


def write_user_circuit(folder, name, points, road_width_m=3.0):
    folder.mkdir(parents=True, exist_ok=True)
    rows = "\n".join(f"  - [{x:.3f}, {y:.3f}]" for x, y in points)
    (folder / f"{name}.yaml").write_text(f"name: {name}\nroad_width_m: {road_width_m}\ncontrol_points_m:\n{rows}\n")


def test_user_circuits_are_found_by_name_and_builtins_win(tmp_path, monkeypatch):
    folder = tmp_path / "mine"
    monkeypatch.setenv("DRIVEBENCH_CIRCUITS_DIR", str(folder))
    assert user_circuits_dir() == folder
    write_user_circuit(folder, "ring", circle(50.0, 24))
    write_user_circuit(folder, "simple", circle(70.0, 24))  # shadowed by the built-in
    assert "ring" in circuit_names() and circuit_names().count("simple") == 1
    assert load_circuit("ring").length_m == pytest.approx(2 * np.pi * 50.0, rel=1e-3)
    assert 430 < load_circuit("simple").length_m < 460


def test_a_bad_user_circuit_is_refused_with_its_problem(tmp_path, monkeypatch):
    monkeypatch.setenv("DRIVEBENCH_CIRCUITS_DIR", str(tmp_path))
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    write_user_circuit(tmp_path, "eight", np.column_stack([100 * np.sin(t), 50 * np.sin(2 * t)]))
    with pytest.raises(CircuitError, match=r"eight\.yaml: the track crosses itself near"):
        load_circuit("eight")


def test_the_default_user_circuits_folder_is_under_home(tmp_path, monkeypatch):
    monkeypatch.delenv("DRIVEBENCH_CIRCUITS_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert user_circuits_dir() == tmp_path / ".local" / "share" / "drivebench" / "circuits"
    assert "simple" in circuit_names()  # an absent folder is no error


# -- pictures ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["simple", "montreal", "random:0"])
def test_circuit_picture_shows_the_road(name, tmp_path):
    circuit = load_circuit(name)
    image = circuit_picture(circuit, width_px=800)
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[1] == 800 and image.shape[2] == 3
    extent = np.ptp(circuit.centreline.points_m, axis=0) + 2 * circuit.road_half_width_m
    scale = 760 / extent[0]  # px per metre: 800 px less two 20 px margins
    assert image.shape[0] == pytest.approx(extent[1] * scale + 2 * 20 + 34, abs=1.01)  # + margins and a text band
    road = np.all(image == ROAD_RGB, axis=2).sum()
    # At least the road's true width (or 2 px) along most of the lap.
    assert road > 0.5 * circuit.length_m * scale * max(2.0, 2 * circuit.road_half_width_m * scale - 2)
    red = (image[:, :, 0] > 180) & (image[:, :, 1] < 80)
    assert red.sum() > 100
    path = save_circuit_picture(circuit, tmp_path / "pictures" / "circuit.png")
    np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB), image)


def test_a_tall_circuit_picture_is_capped_and_centred():
    t = -np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    tall = Circuit("tall", "", "", Centreline(np.column_stack([50 * np.cos(t), 1000 * np.sin(t)])), 1.5, 0.1, 0.5)
    image = circuit_picture(tall, width_px=400)
    assert image.shape == (600 + 34, 400, 3)  # 1.5 x the width, plus the text band
    road_columns = np.flatnonzero(np.all(image == ROAD_RGB, axis=2).any(axis=0))
    assert abs((road_columns.min() + road_columns.max()) / 2 - 200) < 3


@pytest.mark.parametrize("name", ["simple", "montreal", "random:3"])
def test_a_reversed_circuit_is_the_same_road_driven_the_other_way(name):
    forward = load_circuit(name)
    reverse = load_circuit(name, direction="reverse")
    assert reverse.length_m == pytest.approx(forward.length_m, rel=1e-9)
    assert reverse.start_pose()[:2] == pytest.approx(forward.start_pose()[:2])
    turn = np.angle(np.exp(1j * (reverse.start_pose()[2] - forward.start_pose()[2])))
    assert abs(turn) == pytest.approx(np.pi, abs=0.1)
    assert reverse.clockwise != forward.clockwise
    assert {tuple(p) for p in reverse.centreline.points_m} == {tuple(p) for p in forward.centreline.points_m}


def test_every_builtin_circuit_runs_clockwise_forward():
    assert all(load_circuit(name).clockwise for name in builtin_circuit_names())


def test_a_bad_direction_is_refused():
    with pytest.raises(CircuitError, match="direction must be forward or reverse"):
        load_circuit("simple", direction="backwards")


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_a_start_along_the_circuit_is_on_the_centre_line_in_driving_order(direction):
    circuit = load_circuit("simple", direction=direction)
    assert circuit.start_pose() == circuit.centreline.pose_at(0.0)
    assert circuit.start_pose(start_m=40.0) == circuit.centreline.pose_at(40.0)
    # In driving order: 40 m along in reverse is where driving forward reaches 40 m before the start line, facing back.
    other = load_circuit("simple", direction="reverse" if direction == "forward" else "forward")
    x_m, y_m, yaw_rad = circuit.start_pose(start_m=40.0)
    x_other, y_other, yaw_other = other.centreline.pose_at(other.length_m - 40.0)
    assert (x_m, y_m) == pytest.approx((x_other, y_other), abs=1e-9)
    assert abs(np.angle(np.exp(1j * (yaw_rad - yaw_other)))) == pytest.approx(np.pi, abs=0.05)


@pytest.mark.parametrize("start_m", [-1.0, 442.9, 1e9, math.nan, math.inf])
def test_a_start_off_the_circuit_is_one_line_naming_its_length(start_m):
    circuit = load_circuit("simple", direction="reverse")
    with pytest.raises(
        CircuitError, match=r"^start_m must be >= 0 and below 442\.836 m, the length of circuit 'simple', got "
    ):
        circuit.start_pose(start_m=start_m)
