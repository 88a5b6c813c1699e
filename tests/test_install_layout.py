"""drivebench runs whatever the user's current folder holds, and a regular install (a wheel) carries all it needs.

* A folder named like one of drivebench's packages (``circuits/`` of imported tracks, a Behavior Metrics checkout's
  ``brains/`` package, ...) must not shadow drivebench's own: every stack process runs in Python's safe-path mode,
  while ``module:Class`` brains still resolve from the current folder.
* A wheel carries every shipped checkpoint with its shards and the experiments files: ``drivebench run --brain
  pilotnet`` and ``drivebench paper --smoke`` work from an empty folder in a fresh virtual environment.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from support.env import clean_env

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parent.parent
COPY_IGNORED = (".git", ".venv", "runs", "build", "node_modules", "__pycache__", "*.egg-info", ".pytest_cache")
PACKAGE_NAMES = ("circuits", "brains", "services", "protocol", "recorder", "orchestrator")

LOCAL_BRAIN = """\
from brains.explicit.brain import ExplicitBrain


class LocalBrain(ExplicitBrain):
    '''A user's brain in the current folder, found as local_brain:LocalBrain.'''
"""

MATRIX = """\
name: shadowed
brains: [explicit, {name: "local_brain:LocalBrain", label: local}]
circuits: [simple]
limits: {laps: 1, max_sim_seconds: 3}
"""


def shadowing_folder(path: Path) -> Path:
    """A folder holding one folder per drivebench package name, each broken so that importing it fails loudly."""
    path.mkdir(parents=True, exist_ok=True)
    for name in PACKAGE_NAMES:
        (path / name).mkdir()
    # A regular package (as a Behavior Metrics checkout's brains/ is) that fails when imported.
    (path / "brains" / "__init__.py").write_text("raise ImportError('the user folder brains/ was imported')\n")
    (path / "local_brain.py").write_text(LOCAL_BRAIN)
    (path / "matrix.yaml").write_text(MATRIX)
    return path


def run_cli(drivebench: Path, *args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = clean_env()
    return subprocess.run([str(drivebench), *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout)


def assert_drove(result: subprocess.CompletedProcess) -> dict:
    assert result.returncode == 0, result.stderr[-2000:]
    score = json.loads(result.stdout)
    assert score["metrics"]["progress_m"] > 5.0, score["metrics"]
    return score


def installed_command(python: Path) -> Path:
    return python.parent / "drivebench"


def test_a_run_and_a_matrix_ignore_folders_named_like_drivebench_packages(tmp_path):
    folder = shadowing_folder(tmp_path / "work")
    drivebench = installed_command(Path(sys.executable))
    assert_drove(
        run_cli(
            drivebench,
            "run",
            "--circuit",
            "simple",
            "--brain",
            "local_brain:LocalBrain",
            "--max-sim-seconds",
            "3",
            "--json",
            cwd=folder,
        )
    )
    matrix = run_cli(drivebench, "matrix", "matrix.yaml", "-o", "out", cwd=folder)
    assert matrix.returncode == 0, matrix.stderr[-2000:]
    rows = (folder / "out" / "episodes.csv").read_text().splitlines()[1:]
    assert sorted(row.split(",")[1] for row in rows) == ["explicit", "local"], rows
    assert all(",done,time_limit," in row for row in rows), rows


@pytest.mark.slow
def test_a_wheel_in_a_fresh_environment_serves_the_shipped_networks_and_the_paper(tmp_path):
    # Built from a copy: setuptools leaves build/ in the source folder, and a stale one would leak into later wheels.
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, symlinks=True, ignore=shutil.ignore_patterns(*COPY_IGNORED))
    wheels = tmp_path / "wheels"
    built = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(wheels),
            str(source),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = wheels.glob("drivebench-*.whl")

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    # The dependencies come from this environment's site-packages, added as a plain path: its .pth files (the
    # editable install of this checkout among them) are not processed, so drivebench is only the wheel's.
    site = Path(
        subprocess.check_output(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], text=True
        ).strip()
    )
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    installed = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q", str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert installed.returncode == 0, installed.stderr[-2000:]
    where = subprocess.check_output(
        [str(python), "-c", "import orchestrator; print(orchestrator.__file__)"], text=True, cwd=tmp_path
    )
    assert where.startswith(str(site)), where

    drivebench = installed_command(python)
    folder = shadowing_folder(tmp_path / "work")
    assert_drove(
        run_cli(
            drivebench,
            "run",
            "--circuit",
            "simple",
            "--brain",
            "pilotnet",
            "--max-sim-seconds",
            "3",
            "--json",
            cwd=folder,
        )
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    paper = run_cli(drivebench, "paper", "--smoke", "-o", "paper", cwd=empty, timeout=600)
    assert paper.returncode == 0, paper.stderr[-2000:]
    assert (empty / "paper" / "paper.md").is_file()
