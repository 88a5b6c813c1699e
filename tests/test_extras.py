"""Per-role extras: a brain host needs only drivebench's core dependencies.

A brain host runs as a real process in which the stack's extras cannot be imported (each one made unimportable
before anything else runs, as on a machine that never installed them), joins a real local stack and drives an
episode. pyproject's extras are checked to hold every third-party package the other roles import.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

from orchestrator.stack.launcher import LocalStack
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.messages import EndReason

ROOT = Path(__file__).resolve().parent.parent
# What `pip install drivebench` (no extra) leaves out: the simulator, recording, live view, reports, neural brains.
NOT_IN_CORE = (
    "pybullet",
    "scipy",
    "matplotlib",
    "mcap",
    "zstandard",
    "foxglove",
    "foxglove_schemas_protobuf",
    "google.protobuf",
    "torch",
    "onnxruntime",
)
BLOCKED_HOST = f"""
import runpy, sys
for name in {NOT_IN_CORE!r}:
    sys.modules[name] = None  # "import name" now raises ImportError, as where it is not installed
runpy.run_module("brains", run_name="__main__", alter_sys=True)
"""


def test_a_brain_host_without_the_stacks_extras_drives_an_episode(tmp_path):
    with LocalStack(run_id="extras", run_dir=tmp_path, brains=[]) as stack:
        log = open(tmp_path / "brain.log", "wb")
        host = subprocess.Popen(
            [
                sys.executable,
                "-c",
                BLOCKED_HOST,
                "--router",
                stack.endpoint,
                "--run-id",
                "extras",
                "--brain",
                "explicit",
            ],
            cwd=ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            spec = EpisodeSpec(
                max_sim_seconds=2.0, active_brain="explicit", camera=CameraSpec(width_px=96, height_px=72)
            )
            score = stack.run_episode(spec)
        finally:
            host.terminate()
            host.wait(timeout=10)
            log.close()
    assert score.reason == EndReason.TIME_LIMIT, (tmp_path / "brain.log").read_text()
    assert score.metrics.steps == 40 and score.metrics.progress_m > 1.0


def test_the_core_is_small_and_the_stack_extra_holds_every_role():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {requirement.split("=")[0].split(">")[0].split("<")[0] for requirement in project["dependencies"]}
    # shtab: `drivebench completion bash|zsh` (30 kB, pure Python)
    assert core == {"eclipse-zenoh", "msgspec", "numpy", "opencv-python-headless", "pyyaml", "shtab", "tqdm"}
    extras = project["optional-dependencies"]
    assert extras["stack"] == ["drivebench[sim,record,view,report]"]
    everything = " ".join(extras["sim"] + extras["record"] + extras["view"] + extras["report"])
    for package in (
        "pybullet",
        "scipy",
        "mcap",
        "zstandard",
        "foxglove-sdk",
        "foxglove-schemas-protobuf",
        "protobuf",
        "matplotlib",
    ):
        assert package in everything, package
