"""Importing TUM racetrack-database centreline CSVs as user circuits (synthetic files written by the tests)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from circuits import CircuitError, circuit_names, load_circuit
from circuits.importer import import_racetrack_csv
from circuits.library import check_track, min_turn_radius_m
from orchestrator.cli import main

HEADER = "# x_m,y_m,w_tr_right_m,w_tr_left_m\n"


@pytest.fixture(autouse=True)
def user_dir(tmp_path, monkeypatch):
    """The user circuits folder for this test: never the real one."""
    folder = tmp_path / "user-circuits"
    monkeypatch.setenv("DRIVEBENCH_CIRCUITS_DIR", str(folder))
    return folder


def resample(curve: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ~step_m along a densely sampled closed curve (the last point does not repeat the first)."""
    closed = np.vstack([curve, curve[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))])
    count = int(s[-1] // step_m)
    targets = np.linspace(0.0, s[-1], count, endpoint=False)
    return np.column_stack([np.interp(targets, s, closed[:, 0]), np.interp(targets, s, closed[:, 1])])


def ellipse(a_m: float, b_m: float, step_m: float = 5.0) -> np.ndarray:
    t = -np.linspace(0.0, 2 * np.pi, 200_000, endpoint=False)  # clockwise
    return resample(np.column_stack([a_m * np.cos(t), b_m * np.sin(t)]), step_m)


def trefoil(step_m: float = 5.0) -> np.ndarray:
    """A non-convex, non-crossing loop: r = 300 (1 + 0.25 cos 3t), clockwise, offset from the origin."""
    t = -np.linspace(0.0, 2 * np.pi, 200_000, endpoint=False)
    r = 300.0 * (1 + 0.25 * np.cos(3 * t))
    return resample(np.column_stack([r * np.cos(t) + 1000.0, r * np.sin(t) - 500.0]), step_m)


def write_csv(path, points, right_m=5.0, left_m=5.0, *, noise_m=0.0, header=HEADER):
    rng = np.random.default_rng(0)
    points = points + rng.normal(0.0, noise_m, points.shape) if noise_m else points
    right = np.broadcast_to(right_m, len(points))
    left = np.broadcast_to(left_m, len(points))
    body = "".join(f"{x:.4f},{y:.4f},{r:.3f},{lw:.3f}\n" for (x, y), r, lw in zip(points, right, left, strict=True))
    path.write_text(header + body)
    return path


def test_a_full_size_ellipse_imports_and_loads_by_name(tmp_path, user_dir):
    points = ellipse(800.0, 450.0)  # 1.6 x 0.9 km, ~4 km, 5 m spacing
    csv = write_csv(tmp_path / "Ellipse.csv", points, noise_m=0.1)
    written = import_racetrack_csv(csv, name="ellipse")
    assert written == user_dir / "ellipse.yaml"
    assert "ellipse" in circuit_names()
    circuit = load_circuit("ellipse")
    assert circuit.name == "ellipse"
    assert circuit.road_half_width_m == pytest.approx(5.0)
    perimeter = math.pi * (3 * (800 + 450) - math.sqrt((3 * 800 + 450) * (800 + 3 * 450)))  # Ramanujan
    assert circuit.length_m == pytest.approx(perimeter, rel=2e-3)
    assert np.ptp(circuit.centreline.points_m, axis=0) == pytest.approx([1600.0, 900.0], abs=1.0)
    # The smoothed centreline stays on the data (sigma 0.2 m) and starts at the file's first point.
    distances = [abs(circuit.centreline.project(x, y).lateral_m) for x, y in points[::10]]
    assert max(distances) < 0.5
    assert np.hypot(*(circuit.centreline.points_m[0] - points[0])) < 0.5
    # The driving direction is the file's: clockwise here.
    x0, y0, yaw = circuit.start_pose()
    assert yaw == pytest.approx(-math.pi / 2, abs=0.05)
    raw = yaml.safe_load(written.read_text())
    assert raw["source"] == (
        "imported from Ellipse.csv; keep the original data's licence and attribution "
        "(racetrack-database: LGPL-3.0, OpenStreetMap contributors ODbL)"
    )
    assert raw["road_width_m"] == pytest.approx(10.0)


def test_a_non_convex_track_with_uneven_widths_imports_at_a_scale(tmp_path):
    points = trefoil()
    csv = write_csv(tmp_path / "trefoil.csv", points, right_m=3.5, left_m=np.linspace(5.0, 7.0, len(points)))
    import_racetrack_csv(csv, name="trefoil_small", scale=0.25)
    circuit = load_circuit("trefoil_small")
    full = np.sum(np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T))
    assert circuit.length_m == pytest.approx(0.25 * full, rel=5e-3)
    assert 2 * circuit.road_half_width_m == pytest.approx(0.25 * (3.5 + 6.0), rel=1e-3)  # median total width
    check_track(circuit.centreline.points_m, circuit.road_half_width_m)
    assert min_turn_radius_m(circuit.centreline.points_m) > circuit.road_half_width_m


def test_comments_blank_lines_and_an_explicitly_closed_file_are_accepted(tmp_path):
    points = ellipse(100.0, 60.0)
    body = "".join(f"{x:.4f}, {y:.4f}, 1.6, 1.4\n" for x, y in np.vstack([points, points[:1]]))
    csv = tmp_path / "closed.csv"
    csv.write_text("# a comment\n" + HEADER + "\n" + body + "\n# the end\n")
    import_racetrack_csv(csv, name="closed")
    circuit = load_circuit("closed")
    assert circuit.road_half_width_m == pytest.approx(1.5)
    assert circuit.length_m == pytest.approx(
        np.sum(np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)), rel=2e-3
    )


def test_an_existing_user_circuit_is_kept_unless_overwritten(tmp_path):
    csv = write_csv(tmp_path / "a.csv", ellipse(100.0, 60.0))
    import_racetrack_csv(csv, name="my-track.v2")
    with pytest.raises(CircuitError, match="already exists"):
        import_racetrack_csv(csv, name="my-track.v2")
    import_racetrack_csv(csv, name="my-track.v2", scale=2.0, overwrite=True)
    assert load_circuit("my-track.v2").road_half_width_m == pytest.approx(10.0)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("simple", "'simple' is a built-in circuit"),
        ("montreal", "built-in"),
        ("../evil", "bad circuit name"),
        ("random:3", "bad circuit name"),
        ("", "bad circuit name"),
        ("with space", "bad circuit name"),
        (".hidden", "bad circuit name"),
    ],
)
def test_bad_or_clashing_names_are_refused(tmp_path, user_dir, name, message):
    csv = write_csv(tmp_path / "a.csv", ellipse(100.0, 60.0))
    with pytest.raises(CircuitError, match=message):
        import_racetrack_csv(csv, name=name)
    assert not user_dir.exists() or not any(user_dir.iterdir())


def test_a_bad_scale_is_refused(tmp_path):
    csv = write_csv(tmp_path / "a.csv", ellipse(100.0, 60.0))
    for scale in (0.0, -1.0, float("nan")):
        with pytest.raises(CircuitError, match="scale must be a positive number"):
            import_racetrack_csv(csv, name="x", scale=scale)


def lines_of(points, width=5.0):
    return [f"{x:.3f},{y:.3f},{width},{width}" for x, y in points]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda rows: rows[:5], r"bad\.csv: only 5 distinct points; a track needs at least 10"),
        (lambda rows: rows[:6] + ["1.0,2.0,3.0"] + rows[7:], r"bad\.csv:8: expected 4 comma-separated columns .*got 3"),
        (lambda rows: rows[:5] + ["nan,2.0,3.0,3.0"] + rows[6:], r"bad\.csv:7: x_m is not finite: 'nan'"),
        (lambda rows: rows[:5] + ["1.0,inf,3.0,3.0"] + rows[6:], r"bad\.csv:7: y_m is not finite"),
        (lambda rows: rows[:9] + ["1.0,abc,3.0,3.0"] + rows[10:], r"bad\.csv:11: y_m is not a number: 'abc'"),
        (lambda rows: rows[:3] + ["1.0,2.0,0,3.0"] + rows[4:], r"bad\.csv:5: w_tr_right_m must be positive, got 0"),
        (lambda rows: rows[:3] + ["1.0,2.0,3.0,-1"] + rows[4:], r"bad\.csv:5: w_tr_left_m must be positive, got -1"),
    ],
)
def test_bad_csv_files_name_the_line_and_the_problem(tmp_path, edit, message):
    rows = lines_of(ellipse(300.0, 200.0, step_m=5.0))
    csv = tmp_path / "bad.csv"
    csv.write_text(HEADER + "\n".join(edit(rows)) + "\n")
    with pytest.raises(CircuitError, match=message):
        import_racetrack_csv(csv, name="bad")


def test_a_figure_of_eight_is_refused_naming_the_crossing_lines(tmp_path):
    t = np.linspace(0.0, 2 * np.pi, 400, endpoint=False) + 0.01  # not exactly through the crossing point
    eight = np.column_stack([400 * np.sin(t), 200 * np.sin(2 * t)])
    csv = tmp_path / "eight.csv"
    csv.write_text(HEADER + "\n".join(lines_of(eight)) + "\n")
    with pytest.raises(
        CircuitError,
        match=r"eight\.csv: the centreline crosses itself near \(-?0\.\d, -?0\.\d\): "
        r"the segment from line 2\d\d to line 2\d\d crosses the one from line",
    ):
        import_racetrack_csv(csv, name="eight")


def test_a_track_whose_parts_run_too_close_for_its_width_is_refused(tmp_path):
    # A long, thin loop: its two sides 12 m apart, but the road is 14 m wide.
    t = -np.linspace(0.0, 2 * np.pi, 100_000, endpoint=False)
    stadium = resample(np.column_stack([400 * np.cos(t), 6 * np.sin(t)]), 5.0)
    csv = write_csv(tmp_path / "thin.csv", stadium, right_m=7.0, left_m=7.0)
    with pytest.raises(CircuitError, match=r"thin\.csv: after smoothing, .*(pass within|bends with a radius)"):
        import_racetrack_csv(csv, name="thin")


def test_the_command_line_imports_and_reports_errors(tmp_path, user_dir, capsys):
    csv = write_csv(tmp_path / "a.csv", ellipse(100.0, 60.0))
    assert main(["circuits", "import", str(csv), "--name", "cli", "--scale", "0.5"]) == 0
    assert capsys.readouterr().err.strip().endswith(f"-> {user_dir / 'cli.yaml'}")
    assert main(["circuits", "import", str(csv), "--name", "simple"]) == 2
    assert "built-in" in capsys.readouterr().err
