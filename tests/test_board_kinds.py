"""drivebench board, the kinds of submission (issue 42, item 2): a wheel with a ``drivebench.brains`` entry point, an
ONNX network from ``drivebench export`` and a Behavior Metrics brain file are each submitted with ``board submit
--wait --json`` to a real sandboxed server and end scored with intervals; anything else is refused at once with a
reason. And a brain that meets a limit of the sandbox in its contract check ends ``exceeded_limit``.

One sandboxed server serves the module (its start costs seconds); the conditions are the least an evaluation with
intervals can be (a public condition and two hidden ones, 1 s of driving each).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import needs
import pytest
from needs import require
from test_board import GOOD_BRAIN, LOADED_S, Server, last_json, submit

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"
BM_BRAIN = ROOT / "examples" / "behavior_metrics" / "brain_f1_follow_line.py"
SMALL_CONDITIONS = """\
name: small
limits: {laps: 1, max_sim_seconds: 1}
camera: 160x120
parts:
  public: {circuits: [simple]}
  hidden: {draw: {count: 2, circuits: [random, twisty]}}
"""
WHEEL_PROJECT = """\
[build-system]
requires = ["setuptools"]
build-backend = "setuptools.build_meta"

[project]
name = "tinybrain"
version = "0.1"

[project.entry-points."drivebench.brains"]
tiny = "tinybrain.brain:Ahead"

[tool.setuptools]
packages = ["tinybrain"]
"""


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    require("starlette")
    needs.require_bubblewrap()
    folder = tmp_path_factory.mktemp("board")
    conditions = folder / "small.yaml"
    conditions.write_text(SMALL_CONDITIONS)
    server = Server(folder / "data", conditions, sandboxed=True).start()
    yield server
    server.stop()


def build_wheel(folder: Path) -> Path:
    """A tiny brain package built into a wheel by pip, offline (setuptools from this Python's install)."""
    project = folder / "tinybrain-src"
    (project / "tinybrain").mkdir(parents=True)
    (project / "pyproject.toml").write_text(WHEEL_PROJECT)
    (project / "tinybrain" / "__init__.py").write_text("")
    (project / "tinybrain" / "brain.py").write_text(GOOD_BRAIN)
    argv = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index"]
    built = subprocess.run(
        [*argv, "-w", str(folder / "dist"), str(project)], capture_output=True, text=True, timeout=300
    )
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    (wheel,) = (folder / "dist").glob("tinybrain-*.whl")
    return wheel


def export_onnx(folder: Path) -> Path:
    """The shipped DeepestLSTMTinyPilotNet checkpoint, exported by ``drivebench export``."""
    require("torch")
    require("onnxruntime")
    path = folder / "tiny.onnx"
    argv = [sys.executable, "-m", "orchestrator.cli", "export", str(CHECKPOINT), "-o", str(path)]
    exported = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert exported.returncode == 0, exported.stderr[-2000:]
    return path


def behavior_metrics_brain(folder: Path) -> Path:
    """The shipped Behavior Metrics example brain (a ``Brain`` class with ``execute``), under a name of its own."""
    path = folder / "brain_f1_follow_line.py"
    path.write_bytes(BM_BRAIN.read_bytes())
    return path


@pytest.mark.slow
@pytest.mark.timeout(2 * LOADED_S)
@pytest.mark.parametrize(
    ("make", "kind"),
    [(build_wheel, "wheel"), (export_onnx, "onnx"), (behavior_metrics_brain, "behavior_metrics")],
    ids=["wheel", "onnx", "behavior-metrics"],
)
def test_each_kind_of_submission_is_scored_with_intervals_in_the_sandbox(board, tmp_path, make, kind):
    result = submit(board, make(tmp_path), name=kind, wait=True)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    final = last_json(result)
    assert (final["state"], final["kind"]) == ("scored", kind), final
    hidden = final["scores"]["hidden"]
    assert hidden["conditions"] == 2 and "over conditions" in hidden["interval"]
    progress = hidden["progress_iqm"]
    assert progress["low"] <= progress["estimate"] <= progress["high"] and progress["low"] < progress["high"]
    assert [cell["circuit"] for cell in final["scores"]["public"]] == ["simple"]


def hostile_in_init(code: str) -> str:
    """GOOD_BRAIN whose constructor runs ``code`` (one statement per line) everywhere: in the contract check too."""
    lines = "".join(f"        {line}\n" for line in code.splitlines())
    return GOOD_BRAIN.replace(
        "    def reset(self, *, seed: int) -> None:\n",
        f"    def __init__(self):\n        import os, sys\n{lines}\n    def reset(self, *, seed: int) -> None:\n",
    )


OUTSIDE_SCRATCH = ROOT / "tests" / "support" / "hostile" / "written-by-the-board-check.txt"  # bound read-only
HOSTILE_IN_CHECK = {
    "allocates-40-gb": (hostile_in_init("self.kept = bytearray(40 * 2**30)"), "exceeded_limit"),
    "forks-500": (
        hostile_in_init(
            "for _ in range(500):\n    if os.fork() == 0:\n        os.execv('/bin/sleep', ['sleep', '600'])"
        ),
        "exceeded_limit",
    ),
    "prints-a-gigabyte": (
        hostile_in_init("for _ in range(1024):\n    sys.stdout.write('x' * (2**20 - 1) + '\\n')\nsys.stdout.flush()"),
        "exceeded_limit",
    ),
    "writes-outside-its-scratch": (
        hostile_in_init(f"open({str(OUTSIDE_SCRATCH)!r}, 'w').write('escaped')"),
        "sandbox_violation",
    ),
}


@pytest.mark.timeout(2 * LOADED_S)
@pytest.mark.parametrize("hostile", sorted(HOSTILE_IN_CHECK))
def test_a_brain_that_meets_a_wall_in_its_contract_check_is_typed_by_the_wall(board, tmp_path, hostile):
    """Each attack runs in the constructor, so it meets the sandbox in the contract check, before any episode: the
    submission ends with the wall's reason (a limit, or a refused operation), not ``does_not_load``."""
    text, reason = HOSTILE_IN_CHECK[hostile]
    brain = tmp_path / f"{hostile.replace('-', '_')}.py"
    brain.write_text(text)
    result = submit(board, brain, name=hostile, wait=True)
    final = last_json(result)
    assert (final["state"], final["reason"]) == ("rejected", reason), final
    assert not OUTSIDE_SCRATCH.exists()
    check = board.data / "submissions" / final["id"] / "attempt-1" / "check.json"
    assert check.stat().st_size < 2**30  # the gigabyte never reached the server's disk whole


def _zip(entries: dict[str, str]) -> bytes:
    import io
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, text in entries.items():
            archive.writestr(name, text)
    return buffer.getvalue()


REFUSED = {
    "brain.zip": (_zip({"brain.py": GOOD_BRAIN}), "not a brain this server takes"),
    "notes.txt": (b"hello", "not a brain this server takes"),
    "empty.py": (b"x = 1\n", "no brain class"),
    "broken.py": (b"class Ahead(:\n", "not a Python file"),
    "fake.onnx": (b"not a network", "not an ONNX model"),
    "fake.whl": (b"not a zip", "not a wheel"),
    "no-entry-0.1-py3-none-any.whl": (_zip({"tinybrain/brain.py": GOOD_BRAIN}), "0 drivebench.brains entry points"),
    "huge.py": (GOOD_BRAIN.encode() + b"#" * (50 * 2**20), "over the limit"),
}


@pytest.mark.parametrize("filename", sorted(REFUSED))
def test_anything_else_is_refused_at_once_with_one_line_naming_why(board, tmp_path, filename):
    from orchestrator.board.store import BoardStore

    content, why = REFUSED[filename]
    path = tmp_path / filename
    path.write_bytes(content)
    store = BoardStore(board.data)
    try:
        before = len(store.all())
        result = submit(board, path, name="refused")
        assert result.returncode == 2, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1 and why in result.stderr, result.stderr
        assert "Traceback" not in result.stderr
        assert len(store.all()) == before  # nothing queued
    finally:
        store.close()
