"""Import a TUM racetrack-database centreline CSV as a user circuit.

The racetrack-database (github.com/TUMFTM/racetrack-database, LGPL-3.0, built from OpenStreetMap data, ODbL) has
one ``tracks/NAME.csv`` per circuit: comment lines start with ``#``; every other line is
``x_m,y_m,w_tr_right_m,w_tr_left_m`` (a centreline point in metres and the distances from it to the right and left
track edges), in driving order, about 5 m apart. The loop is implicitly closed: the last point does not repeat the
first (a file that does repeat it is accepted too). drivebench bundles none of that data; a user downloads a file
and imports it::

    drivebench circuits import Catalunya.csv --name catalunya [--scale 1.0]

:func:`import_racetrack_csv` then

1. reads and validates the file; every error is one line naming the file and, where it applies, the line
   (fewer than :data:`MIN_POINTS` points, a wrong column count, a non-number, NaN or infinity, a width <= 0, a
   centreline that crosses itself);
2. multiplies every coordinate and width by ``scale`` (1.0 = real size);
3. smooths the centreline with a periodic smoothing cubic spline (``scipy.interpolate.splprep(per=1, s=...)``) with
   smoothing factor ``s = N * sigma**2``, N the number of points and sigma = :data:`SMOOTHING_FRACTION` of the road
   width (0.2 m on a 10 m road): the spline may pass about sigma (RMS) from the points, which irons out the
   survey ripple that would otherwise read as curvature noise, and keeps it well inside the road;
4. resamples that spline at the data's own median point spacing (scaled) as the circuit's control points, which
   the loader turns back into a centreline with the usual interpolating periodic spline (the two agree to
   millimetres);
5. checks the result with :func:`~circuits.library.check_track` (no crossing, the walls of two parts of
   the track at least 0.5 m apart, no bend tighter than the half-width);
6. writes ``NAME.yaml`` (the usual circuit format, see ``circuits/data/simple.yaml``) into the user
   circuits folder, ``$DRIVEBENCH_CIRCUITS_DIR`` or ``~/.local/share/drivebench/circuits``, with
   road_width_m = the median of (w_tr_right_m + w_tr_left_m), scaled, and a ``source`` that carries the data's
   licence and attribution along.

The road is drawn at that constant width centred on the centreline (the data's centreline is not always in the
middle of the real track, nor are its widths constant). The start is the file's first point; the driving direction
is the file's order.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
from scipy.interpolate import splev, splprep

from circuits.library import (
    PLAIN_NAME,
    RESAMPLE_STEP_M,
    CircuitError,
    builtin_circuit_names,
    check_track,
    closed_spline,
    find_crossing,
    user_circuits_dir,
)

MIN_POINTS = 10
COLUMNS = ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")
SMOOTHING_FRACTION = 0.02  # sigma of the smoothing spline, as a fraction of the road width
LINE_WIDTH_M = 0.10
WALL_HEIGHT_M = 0.5
LICENCE_NOTE = (
    "keep the original data's licence and attribution (racetrack-database: LGPL-3.0, OpenStreetMap contributors ODbL)"
)


def import_racetrack_csv(path: str | Path, *, name: str, scale: float = 1.0, overwrite: bool = False) -> Path:
    """Convert a racetrack-database centreline CSV into the user circuit ``name``; returns the YAML file written.

    ``scale`` multiplies every length (e.g. ~0.15 to bring a 5 km F1 track down to Behavior Metrics' size).
    Raises :class:`CircuitError` (one line, naming the file and line) for a bad file, a bad or built-in name, or an
    existing user circuit of that name unless ``overwrite``.
    """
    path = Path(path)
    if not isinstance(name, str) or not PLAIN_NAME.fullmatch(name):
        raise CircuitError(
            f"bad circuit name {name!r}: use 1-64 letters, digits, '_', '-' or '.', starting with a letter or digit"
        )
    if name in builtin_circuit_names():
        raise CircuitError(f"{name!r} is a built-in circuit; choose another name")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise CircuitError(f"scale must be a positive number, got {scale!r}")
    target = user_circuits_dir() / f"{name}.yaml"
    if target.exists() and not overwrite:
        raise CircuitError(
            f"a user circuit named {name!r} already exists ({target}): choose another name, or overwrite it"
        )

    points, widths, lines = read_racetrack_csv(path)
    points = points * scale
    road_width = float(np.median(widths.sum(axis=1))) * scale
    control = smooth_centreline(points, road_width_m=road_width)
    try:
        check_track(closed_spline(control, step_m=RESAMPLE_STEP_M), road_width / 2)
    except CircuitError as error:
        raise CircuitError(f"{path}: after smoothing, {error}") from None

    length = float(np.sum(np.hypot(*np.diff(np.vstack([control, control[:1]]), axis=0).T)))
    rows = "\n".join(f"  - [{x:.3f}, {y:.3f}]" for x, y in control)
    text = (
        f"# Imported by drivebench from {path.name} (TUM racetrack-database format) at scale {scale:g}:\n"
        f"# {len(points)} points on lines {lines[0]}-{lines[-1]}, smoothed with a periodic smoothing spline\n"
        f"# (sigma {SMOOTHING_FRACTION * road_width:.3f} m) and resampled as {len(control)} control points.\n"
        f"# {LICENCE_NOTE[0].upper()}{LICENCE_NOTE[1:]}.\n"
        f"name: {name}\n"
        f"description: {json.dumps(f'imported from {path.name} at scale {scale:g}, about {length:.0f} m')}\n"
        f"source: {json.dumps(f'imported from {path.name}; {LICENCE_NOTE}')}\n"
        f"road_width_m: {road_width:.3f}\n"
        f"line_width_m: {LINE_WIDTH_M}\n"
        f"wall_height_m: {WALL_HEIGHT_M}\n"
        f"control_points_m:\n{rows}\n"
    )
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=target.parent, prefix=f".{name}.", suffix=".tmp", delete=False) as tmp:
        tmp.write(text)
    os.replace(tmp.name, target)
    return target


def read_racetrack_csv(path: Path) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(points (N, 2), widths (N, 2) right/left, line number of each point) of a racetrack-database CSV.

    Blank lines and lines starting with '#' are skipped. Consecutive repeated points are dropped, and so is a last
    point that repeats the first (an explicitly closed file).
    """
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as error:
        raise CircuitError(f"{path}: cannot read: {error}") from None
    rows: list[list[float]] = []
    lines: list[int] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = [field.strip() for field in line.split(",")]
        if len(fields) != len(COLUMNS):
            raise CircuitError(
                f"{path}:{number}: expected {len(COLUMNS)} comma-separated columns ({','.join(COLUMNS)}), "
                f"got {len(fields)}"
            )
        values = []
        for column, field in zip(COLUMNS, fields, strict=True):
            try:
                value = float(field)
            except ValueError:
                raise CircuitError(f"{path}:{number}: {column} is not a number: {field!r}") from None
            if not math.isfinite(value):
                raise CircuitError(f"{path}:{number}: {column} is not finite: {field!r}")
            values.append(value)
        if values[2] <= 0 or values[3] <= 0:
            column = COLUMNS[2] if values[2] <= 0 else COLUMNS[3]
            raise CircuitError(f"{path}:{number}: {column} must be positive, got {values[COLUMNS.index(column)]:g}")
        if rows and values[:2] == rows[-1][:2]:
            continue  # a repeated point
        rows.append(values)
        lines.append(number)
    if len(rows) > 1 and rows[-1][:2] == rows[0][:2]:
        rows.pop()
        lines.pop()
    if len(rows) < MIN_POINTS:
        raise CircuitError(f"{path}: only {len(rows)} distinct points; a track needs at least {MIN_POINTS}")
    data = np.asarray(rows, dtype=float)
    points = data[:, :2]
    crossing = find_crossing(points)
    if crossing is not None:
        i, j, x, y = crossing
        n = len(points)
        raise CircuitError(
            f"{path}: the centreline crosses itself near ({x:.1f}, {y:.1f}): the segment from line {lines[i]} to "
            f"line {lines[(i + 1) % n]} crosses the one from line {lines[j]} to line {lines[(j + 1) % n]}"
        )
    return points, data[:, 2:], lines


def smooth_centreline(points_m: np.ndarray, *, road_width_m: float) -> np.ndarray:
    """Control points for a circuit file: a periodic smoothing spline through the closed polyline (sigma =
    SMOOTHING_FRACTION of the road width), sampled at the polyline's median point spacing."""
    closed = np.vstack([points_m, points_m[:1]])
    spacing = np.hypot(*np.diff(closed, axis=0).T)
    sigma = SMOOTHING_FRACTION * road_width_m
    tck, _ = splprep([closed[:, 0], closed[:, 1]], s=len(points_m) * sigma**2, per=1, quiet=1)
    dense_u = np.linspace(0.0, 1.0, 20 * len(closed), endpoint=False)
    dense = np.stack(splev(dense_u, tck), axis=1)
    s_dense = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(np.vstack([dense, dense[:1]]), axis=0).T))])
    step = float(np.median(spacing))
    count = max(MIN_POINTS, round(s_dense[-1] / step))
    u = np.interp(np.linspace(0.0, s_dense[-1], count, endpoint=False), s_dense, np.append(dense_u, 1.0))
    return np.stack(splev(u, tck), axis=1)
