"""End to end: importing a real-scale track and driving it; circuits list / show; the test circuits driven."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import cv2
import pytest

pytestmark = pytest.mark.integration


def drivebench(*args: str, env: dict | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True, timeout=timeout, env=env
    )


@pytest.fixture
def circuits_env(tmp_path, monkeypatch):
    monkeypatch.setenv("DRIVEBENCH_CIRCUITS_DIR", str(tmp_path / "circuits"))
    import os

    return dict(os.environ)


def write_ellipse_csv(path, *, a_m: float = 800.0, b_m: float = 450.0, spacing_m: float = 5.0) -> None:
    """A racetrack-database-format centreline: an F1-scale ellipse (~4 km), 10 m wide, implicitly closed."""
    count = int(2 * math.pi * math.sqrt((a_m**2 + b_m**2) / 2) / spacing_m)
    lines = ["# x_m,y_m,w_tr_right_m,w_tr_left_m"]
    for i in range(count):
        t = -2 * math.pi * i / count  # clockwise, like the built-in circuits
        lines.append(f"{a_m * math.cos(t):.3f},{b_m * math.sin(t):.3f},5.0,5.0")
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.slow
def test_imported_f1_scale_track_is_driven_by_the_explicit_brain(tmp_path, circuits_env):
    csv = tmp_path / "oval.csv"
    write_ellipse_csv(csv)
    imported = drivebench("circuits", "import", str(csv), "--name", "oval", env=circuits_env)
    assert imported.returncode == 0, imported.stderr
    listed = drivebench("circuits", "list", env=circuits_env)
    assert "oval" in listed.stdout and "simple" in listed.stdout
    result = drivebench(
        "run", "--circuit", "oval", "--max-sim-seconds", "40", "--json", "--out", str(tmp_path / "r"), env=circuits_env
    )
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout)
    assert score["reason"] == "time_limit"  # it kept on the road for 40 s
    assert score["metrics"]["progress_m"] > 250
    assert score["metrics"]["cross_track_mean_m"] < 0.5


def test_bad_csv_is_one_line_naming_the_line(tmp_path, circuits_env):
    csv = tmp_path / "bad.csv"
    write_ellipse_csv(csv)
    lines = csv.read_text().splitlines()
    lines[6] = "12.0,nan,5.0,5.0"
    csv.write_text("\n".join(lines) + "\n")
    result = drivebench("circuits", "import", str(csv), "--name", "bad", env=circuits_env, timeout=60)
    assert result.returncode == 2
    assert "bad.csv:7: y_m is not finite" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_show_writes_a_picture(tmp_path, circuits_env):
    out = tmp_path / "simple.png"
    result = drivebench("circuits", "show", "simple", "-o", str(out), env=circuits_env, timeout=60)
    assert result.returncode == 0, result.stderr
    picture = cv2.imread(str(out))
    assert picture is not None and picture.shape[1] == 800


def test_list_names_every_generated_family_and_show_draws_one(tmp_path, circuits_env):
    listed = json.loads(drivebench("circuits", "list", "--json", env=circuits_env, timeout=60).stdout)
    generated = {item["name"] for item in listed if item["length_m"] is None}
    assert generated == {"random:SEED", "twisty:SEED", "grandprix:SEED"}
    out = tmp_path / "gp.png"
    result = drivebench("circuits", "show", "grandprix:3", "-o", str(out), env=circuits_env, timeout=60)
    assert result.returncode == 0, result.stderr
    assert cv2.imread(str(out)) is not None and "grandprix:3" in result.stderr


@pytest.mark.slow
@pytest.mark.parametrize("circuit", ["montmelo", "nurburgring"])
def test_explicit_brain_completes_a_lap_over_zenoh(circuit, tmp_path):
    result = drivebench("run", "--circuit", circuit, "--json", "--out", str(tmp_path / "r"), timeout=300)
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout)
    assert score["reason"] == "laps_completed", score["reason"]
    assert score["metrics"]["cross_track_mean_m"] < 0.25
