"""``drivebench brains check`` on brains that are slow or talk: progress, an early stop once the answer-time check has
failed, partial results on Ctrl-C, and a report the brain's own prints cannot bury or imitate. Real subprocesses of
the CLI, real rendered frames."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from brains.checker import answer_time_fails

ROOT = Path(__file__).resolve().parent.parent
CHECK_NAMES = ("make", "protocol", "act", "read-only", "units", "answer time", "determinism", "memory")

BRAINS = '''
import time
from brains.base import Action


class Loud:
    """Prints lines that look like the checker's report, on every call."""
    def __init__(self):
        print("PASS  fake        constructor says all is well")
    def reset(self, *, seed):
        print("PASS  fake        reset")
    def act(self, observation):
        print("PASS  fake        act")
        return Action(speed_mps=2.0, yaw_rate_radps=0.1)


class Slow:
    """Takes SECONDS per frame."""
    SECONDS = 0.6
    def reset(self, *, seed):
        pass
    def act(self, observation):
        time.sleep(self.SECONDS)
        return Action(speed_mps=2.0, yaw_rate_radps=0.1)
'''


@pytest.fixture
def brain_dir(tmp_path: Path) -> Path:
    (tmp_path / "talking_brains.py").write_text(BRAINS)
    return tmp_path


def check_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "orchestrator.cli", "brains", "check", *args]


def env_for(brain_dir: Path) -> dict[str, str]:
    path = os.pathsep.join(filter(None, [str(brain_dir), str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return os.environ | {"PYTHONPATH": path, "PYTHONUNBUFFERED": "1"}


def report_lines(stdout: str) -> list[str]:
    """Lines of the report: a check's line or its fix."""
    return [line for line in stdout.splitlines() if line.strip()]


def test_a_brain_that_prints_cannot_bury_or_imitate_the_report(brain_dir):
    done = subprocess.run(
        check_command("talking_brains:Loud", "--memory-steps", "4"),
        capture_output=True,
        text=True,
        timeout=300,
        cwd=brain_dir,
        env=env_for(brain_dir),
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "fake" not in done.stdout
    lines = report_lines(done.stdout)
    assert [line.split(maxsplit=1)[1].startswith(CHECK_NAMES) for line in lines] == [True] * len(lines)
    assert len(lines) == len(CHECK_NAMES) and all(line.startswith(("PASS", "WARN")) for line in lines)
    assert "the brain printed" in done.stderr and "brain| PASS  fake        act" in done.stderr  # marked as its own


def test_a_brain_slower_than_the_lock_step_timeout_stops_the_check_early_and_says_so(brain_dir):
    started = time.monotonic()
    done = subprocess.run(
        check_command("talking_brains:Slow", "--brain-timeout", "0.3"),
        capture_output=True,
        text=True,
        timeout=300,
        cwd=brain_dir,
        env=env_for(brain_dir),
    )
    took_s = time.monotonic() - started
    assert done.returncode == 1, done.stdout + done.stderr
    lines = {line[6:].split(maxsplit=1)[0]: line for line in report_lines(done.stdout) if not line.startswith(" ")}
    assert lines["act"].startswith("PASS") and "4 of 48 frames" in lines["act"]
    answer = next(line for line in done.stdout.splitlines() if line[6:].startswith("answer time"))
    assert answer.startswith("FAIL") and "stopped early" in answer and "4 of the first 4 frames" in answer
    assert lines["determinism"].startswith("SKIP") and lines["memory"].startswith("SKIP")
    assert "... act: " in done.stderr  # progress while it acted
    # All checks at 0.6 s a frame would take over 7 minutes (~700 frames): it stopped after 4.
    assert took_s < 240


def test_ctrl_c_prints_the_results_so_far(brain_dir):
    env = env_for(brain_dir)
    process = subprocess.Popen(
        check_command("talking_brains:Slow"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=brain_dir,
        env=env,
    )
    try:
        deadline = time.monotonic() + 240
        stderr = ""
        while "... act: frame" not in stderr:  # it is acting (0.6 s a frame): make and protocol are done
            assert process.poll() is None and time.monotonic() < deadline, stderr
            stderr += os.read(process.stderr.fileno(), 4096).decode()
        process.send_signal(signal.SIGINT)
        stdout, rest = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    stderr += rest
    assert process.returncode == 130, stdout + stderr
    assert [line[:4] + line[6:].split(maxsplit=1)[0] for line in report_lines(stdout)] == ["PASSmake", "PASSprotocol"]
    assert "interrupted during act" in stderr and "2 check(s) done" in stderr and "Traceback" not in stderr


def test_an_answer_time_fails_early_only_when_no_later_frames_can_save_it():
    assert not answer_time_fails([11.0] * 3, total=48, brain_timeout_s=10.0)  # p95 of 48 may still be under 10 s
    assert answer_time_fails([11.0] * 4, total=48, brain_timeout_s=10.0)  # not any more: 4 of 48 over it
    assert not answer_time_fails([0.1] * 47, total=48, brain_timeout_s=10.0)
    assert answer_time_fails([20.0], total=1, brain_timeout_s=10.0)
