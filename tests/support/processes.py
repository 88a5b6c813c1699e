"""A launcher of ``python -m module`` processes for a test: one log file each, started in their own session,
stopped (terminated, then killed) after the test."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from support.waits import wait_for

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Processes:
    """Children by name, each logging to ``logs/<name>.log``."""

    logs: Path
    children: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, name: str, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
        with open(self.logs / f"{name}.log", "ab") as log:
            process = subprocess.Popen(
                [sys.executable, "-m", *argv],
                cwd=ROOT,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
            )
        self.children[name] = process
        return process

    def log(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text(errors="replace")

    def dead(self) -> str | None:
        """Which child has exited, with its code and log tail; None while all run."""
        for name, process in self.children.items():
            if process.poll() is not None:
                return f"{name} exited with {process.returncode}: {self.log(name)[-1500:]}"
        return None

    def wait_for_log(self, name: str, text: str, timeout_s: float = 30) -> None:
        try:
            wait_for(
                lambda: text in self.log(name), timeout_s=timeout_s, what=f"{name} to log {text!r}", alive=self.dead
            )
        except AssertionError as error:
            raise AssertionError(f"{error}; its log ends: {self.log(name)[-1500:]}") from None

    def stop(self) -> None:
        for process in self.children.values():
            if process.poll() is None:
                process.terminate()
        for process in self.children.values():
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def environment_of(pid: int) -> dict[str, str]:
    """The environment a running process was started with (Linux: /proc/PID/environ)."""
    raw = Path(f"/proc/{pid}/environ").read_bytes().decode()
    return dict(item.split("=", 1) for item in raw.split("\0") if "=" in item)
