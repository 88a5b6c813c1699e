"""Bring your own brain: every route a user's brain takes into drivebench drives a real lap of ``simple``.

* an installed package's brain, found by the ``drivebench.brains`` entry point (``examples/my_brain``, which
  ``scripts/setup.sh`` installs as a user would install theirs);
* a ``module:Class`` path from the user's own folder;
* a brain process written without drivebench (``examples/standalone_brain``: only zenoh and msgpack);
* a Behavior Metrics brain file, run unchanged (``examples/behavior_metrics``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support.env import clean_env

from orchestrator.stack.launcher import LocalStack
from protocol import keys
from protocol.bus import ANSWER_TIMEOUT_S
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parent.parent
BM_EXAMPLE = ROOT / "examples" / "behavior_metrics" / "brain_f1_follow_line.py"
STANDALONE = ROOT / "examples" / "standalone_brain" / "zenoh_brain.py"
COMPARE = ROOT / "examples" / "my_brain" / "compare.yaml"
LAP_LIMIT_S = "150"


def drivebench(*args: str, cwd: Path | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    env = clean_env()
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=timeout,
    )


def lap_score(result: subprocess.CompletedProcess) -> dict:
    assert result.returncode == 0, result.stderr[-2000:]
    score = json.loads(result.stdout)
    assert score["reason"] == EndReason.LAPS_COMPLETED, score["reason"]
    assert score["metrics"]["completed_laps"] == 1
    return score


@pytest.mark.slow
def test_an_installed_package_brain_drives_a_lap_by_its_entry_point_name(tmp_path):
    listed = drivebench("brains", "list")
    assert "my_brain" in listed.stdout and "entry point of drivebench-my-brain" in listed.stdout, (
        "examples/my_brain is not installed: run scripts/setup.sh"
    )
    score = lap_score(
        drivebench(
            "run", "--brain", "my_brain", "--max-sim-seconds", LAP_LIMIT_S, "--json", "--out", str(tmp_path / "run")
        )
    )
    assert score["brain"] == "my_brain"


LAP_BRAIN = '''
from brains.base import Action
from brains.explicit.brain import ExplicitBrain


class SteadyExplicit:
    """The user's own class: the explicit brain's steering at a steady 9 m/s."""
    def __init__(self, *, speed_mps=9.0):
        self.inner, self.speed_mps = ExplicitBrain(), speed_mps
    def reset(self, *, seed):
        self.inner.reset(seed=seed)
    def act(self, observation):
        return Action(speed_mps=self.speed_mps, yaw_rate_radps=self.inner.act(observation).yaw_rate_radps)
'''


@pytest.mark.slow
def test_a_module_path_brain_from_the_users_folder_drives_a_lap(tmp_path):
    (tmp_path / "lap_brain.py").write_text(LAP_BRAIN)
    score = lap_score(
        drivebench(
            "run",
            "--brain",
            "lap_brain:SteadyExplicit",
            "--brain-option",
            "speed_mps=9",
            "--max-sim-seconds",
            LAP_LIMIT_S,
            "--json",
            "--out",
            str(tmp_path / "run"),
            cwd=tmp_path,
        )
    )
    assert score["brain"] == "SteadyExplicit"  # its bus name: the class name
    assert 8.5 < score["metrics"]["average_speed_mps"] < 9.5


@pytest.mark.slow
def test_a_behavior_metrics_brain_file_drives_a_lap_unchanged(tmp_path):
    score = lap_score(
        drivebench(
            "run",
            "--brain",
            str(BM_EXAMPLE),
            "--max-sim-seconds",
            LAP_LIMIT_S,
            "--json",
            "--out",
            str(tmp_path / "run"),
        )
    )
    assert score["brain"] == "brain_f1_follow_line"


BM_BRAIN_WITH_OWN_LISTS = """
import time


class Brain:
    # As BM's neural brains: its own timings of predict only, and its own suddenness values, one per step
    def __init__(self, sensors, actuators, model=None, handler=None, config=None):
        self.motors = actuators.get_motor("motors_0")
        self.inference_times = []
        self.suddenness_distance = []
        self.gpu_inference = True

    def execute(self):
        time.sleep(0.01)  # work outside the model (BM's brains apply their perturbation here)
        self.inference_times.append(0.004)
        self.suddenness_distance.append(0.125)
        self.motors.sendV(2.0)
        self.motors.sendW(0.0)
"""


def test_bm_metrics_come_from_a_bm_brains_own_lists_beside_drivebenchs_step_time(tmp_path):
    """BM's mean_inference_time is the mean of the brain's own inference_times (its model only), and its
    suddenness_distance the mean of the brain's own list; drivebench's step time (the whole execute(), 10 ms of
    work outside the model here) and its command-based suddenness stay beside them; gpu_inference is the brain's."""
    brain = tmp_path / "brain_own_lists.py"
    brain.write_text(BM_BRAIN_WITH_OWN_LISTS)
    result = drivebench(
        "run",
        "--brain",
        str(brain),
        "--camera",
        "160x120",
        "--max-sim-seconds",
        "3",
        "--json",
        "--out",
        str(tmp_path / "run"),
    )
    assert result.returncode == 0, result.stderr[-2000:]
    metrics = json.loads(result.stdout)["metrics"]
    assert metrics["bm_mean_inference_time_s"] == pytest.approx(0.004)
    assert metrics["bm_suddenness_distance"] == pytest.approx(0.125)
    assert metrics["mean_inference_time_s"] > 0.009  # the whole step, the 10 ms outside the model included
    assert metrics["suddenness_distance"] == 0.0  # constant commands
    assert metrics["gpu_inference"] is True
    assert metrics["frame_rate_hz"] == pytest.approx(20.0)
    assert metrics["brain_iterations_frequency_simulated_time_hz"] == pytest.approx(20.0, rel=0.05)
    assert 0 < metrics["brain_iterations_frequency_real_time_hz"] < 100
    assert metrics["circuit_diameter_m"] is None  # no lap in 3 s


@pytest.mark.slow
def test_a_standalone_zenoh_brain_without_project_code_drives_a_lap(tmp_path):
    source = STANDALONE.read_text()
    assert not [
        line
        for line in source.splitlines()
        if line.startswith(("import ", "from "))
        and line.split()[1].split(".")[0] not in ("argparse", "threading", "time", "msgpack", "zenoh")
    ], "the example may only use zenoh and msgpack"
    with LocalStack(run_id="standalone", run_dir=tmp_path / "stack", brains=[]) as stack:
        log = open(tmp_path / "brain.log", "wb")
        brain = subprocess.Popen(
            [
                sys.executable,
                str(STANDALONE),
                "--router",
                stack.endpoint,
                "--run-id",
                stack.run_id,
                "--name",
                "line_follower",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=tmp_path,
        )  # not the repository: nothing of drivebench is importable by path
        try:
            token = keys.alive(stack.run_id, "brain", "line_follower")
            deadline = time.monotonic() + 30
            while token not in stack.bus.alive_now(token) and time.monotonic() < deadline:
                assert brain.poll() is None, (tmp_path / "brain.log").read_text()
            score = stack.run_episode(
                EpisodeSpec(circuit="simple", active_brain="line_follower", max_sim_seconds=float(LAP_LIMIT_S))
            )
            assert score.reason == EndReason.LAPS_COMPLETED, score.reason
            assert score.metrics.completed_laps == 1 and score.metrics.command_rate_hz > 19
            reply = stack.bus.request(
                keys.brain_control(stack.run_id, "line_follower"), b"\x81\xa6action\xa4stop", timeout_s=ANSWER_TIMEOUT_S
            )  # msgpack {"action": "stop"}
            assert reply is not None
            assert brain.wait(timeout=10) == 0  # stopped over its control key, cleanly
        finally:
            brain.kill()
            log.close()


def test_the_my_brain_example_matrix_runs_in_its_smoke_form(tmp_path):
    result = drivebench("matrix", str(COMPARE), "--smoke", "-o", str(tmp_path / "m"), timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    report = (tmp_path / "m" / "report.md").read_text()
    assert "my_brain" in report and "explicit" in report
    plan = drivebench("matrix", str(COMPARE), "--smoke", "--plan").stdout
    episodes = [line.split()[1] for line in plan.splitlines()[1:]]
    assert len(episodes) == 8 and all(key.endswith("/r0") for key in episodes)  # 2 brains x 2 circuits x 2 noises
    assert {key.split("/")[0] for key in episodes} == {"my_brain", "explicit"}


BAD_VALUE_BRAIN = '''
from brains.base import Action


class Wild:
    """Drives straight for a few frames, then answers one value no car can take."""
    def __init__(self, *, field, value, after=5):
        self.field, self.value, self.after = field, float(value), after
    def reset(self, *, seed):
        pass
    def act(self, observation):
        command = {"speed_mps": 2.0, "yaw_rate_radps": 0.0}
        if observation.seq >= self.after:
            command[self.field] = self.value
        return Action(**command)
'''


@pytest.mark.parametrize(
    "field, value, shown, mode",
    [
        ("speed_mps", "nan", "nan", "--lockstep"),
        ("yaw_rate_radps", "-inf", "-inf", "--lockstep"),
        ("speed_mps", "1e300", "1e+300", "--lockstep"),
        ("speed_mps", "nan", "nan", "--realtime"),
    ],
    ids=["nan", "-inf", "1e300", "nan-realtime"],
)
def test_a_brain_that_answers_a_value_no_car_can_take_ends_its_episode_brain_invalid(
    tmp_path, field, value, shown, mode
):
    """NaN killed the simulator and 1e300 the scorer: the answer is refused where it enters, the episode ends typed
    as the brain's fault with the value, and is scored; the run exits 0 (whatever the brain did)."""
    (tmp_path / "wild_brain.py").write_text(BAD_VALUE_BRAIN)
    run_dir = tmp_path / "run"
    result = drivebench(
        "run",
        "--brain",
        "wild_brain:Wild",
        "--brain-option",
        f"field={field}",
        "--brain-option",
        f"value={value}",
        "--camera",
        "64x48",
        "--max-sim-seconds",
        "20",
        *(["--realtime"] if mode == "--realtime" else []),
        "--json",
        "--out",
        str(run_dir),
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    score = json.loads(result.stdout)
    assert score["reason"] == EndReason.BRAIN_INVALID
    assert f"{field}={shown}" in score["detail"] and "Wild" in score["detail"], score["detail"]
    if mode == "--lockstep":
        assert score["metrics"]["steps"] == 5  # frames 0-4 were driven; the answer to frame 5 was refused
    else:  # the latest answer drives: a few frames may pass before the refused one is the latest
        assert 5 <= score["metrics"]["steps"] < 400
    logs = "".join(path.read_text() for path in run_dir.rglob("*.log"))
    assert "Traceback" not in logs
