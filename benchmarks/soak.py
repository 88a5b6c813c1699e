"""Soak: many short episodes through one warm stack, and whether any process grows.

    .venv/bin/python benchmarks/soak.py [--episodes 500] [--early 50] [--renderer gl] [--noise salt_pepper=0.1]

One worker runs ``--episodes`` short episodes (explicit brain, ``simple``, 1 s sim, 96x72 camera, with noise so that
the noise injector does real work) on one warm stack. Right after the ``--early``-th and the ``--episodes``-th episode
(before the next one starts: one more episode is run than measured) it reads from /proc, for each role (the matrix
driver, i.e. this process, the simulator, noise injector, scorer and brain host), resident memory and open file
descriptors, and prints both and the change (and a line of the same after every ``--early`` episodes, as it goes).
Flat after warm-up is the goal; the table says what grew.
With ``--record`` each episode also gets a recorder, started and stopped per episode (so its row
is a new process each time).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

from orchestrator.matrix.load import parse_matrix
from orchestrator.matrix.results import EpisodeResult
from orchestrator.matrix.runner import MatrixProgress, MatrixRunner, RunOptions
from protocol import environment

ROLES = {  # role -> what its command line holds (every stack process runs ``python -P -m <module>``)
    "simulator": " -m services.simulator ",
    "noise injector": " -m services.noise ",
    "scorer": " -m services.scorer ",
    "brain host": " -m brains ",
    "recorder": " -m recorder ",
}


def matrix_text(*, episodes: int, renderer: str, noise: str) -> str:
    return (
        f"name: soak\nbrains: [explicit]\ncircuits: [simple]\nrepetitions: {episodes}\n"
        f"perturbations: [{noise}]\nlimits: {{laps: 1, max_sim_seconds: 1}}\ncamera: 96x72\nrenderer: {renderer}\n"
    )


def children_of_this_driver() -> dict[str, int]:
    """Role -> pid of the stack processes this process started (they carry our pid in their environment)."""
    marker = f"{environment.PARENT_PID.name}={os.getpid()}".encode()
    found: dict[str, int] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker not in (entry / "environ").read_bytes().split(b"\0"):
                continue
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace") + " "
        except OSError:
            continue
        for role, text in ROLES.items():
            if text in cmdline:
                found[role] = int(entry.name)
    return found


class Usage(NamedTuple):
    """What one process holds at one moment."""

    pid: int
    mb: float  # resident memory
    fds: int  # open file descriptors


def usage(pid: int) -> Usage:
    """Resident memory and open file descriptors of one process, from /proc."""
    status = Path(f"/proc/{pid}/status").read_text()
    rss_kb = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
    return Usage(pid, rss_kb / 1024, len(os.listdir(f"/proc/{pid}/fd")))


def snapshot() -> dict[str, Usage]:
    """Role -> its process's usage, the driver (this process) included."""
    pids = {"matrix driver": os.getpid(), **children_of_this_driver()}
    rows = {}
    for role, pid in pids.items():
        try:
            rows[role] = usage(pid)
        except (OSError, StopIteration):
            continue
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=500, help="episodes measured (one more is run)")
    parser.add_argument("--early", type=int, default=50, help="the first measurement, after this many episodes")
    parser.add_argument("--renderer", default="gl")
    parser.add_argument("--noise", default="salt_pepper=0.1")
    parser.add_argument("--record", action="store_true", help="record every episode (a recorder per episode)")
    args = parser.parse_args()
    if not 1 <= args.early < args.episodes:
        parser.error("need 1 <= --early < --episodes")
    marks: dict[int, dict[str, Usage] | None] = {args.early: None, args.episodes: None}  # episode -> snapshot
    text = matrix_text(episodes=args.episodes + 1, renderer=args.renderer, noise=args.noise)

    def measure(result: EpisodeResult, progress: MatrixProgress) -> None:
        """In the worker thread, right after an episode's result is counted: its stack is still up."""
        finished = progress.done + progress.failed
        if finished in marks or finished % args.early == 0:
            rows = snapshot()
            if finished in marks:
                marks[finished] = rows
            line = ", ".join(f"{role} {mb:.1f} MB {fds} fds" for role, (_, mb, fds) in rows.items())
            print(f"after episode {finished} ({time.monotonic() - started:.0f} s): {line}", flush=True)

    started = time.monotonic()
    with tempfile.TemporaryDirectory() as folder:
        runner = MatrixRunner(
            parse_matrix(text), Path(folder), RunOptions(workers=1, record=args.record), on_result=measure
        )
        progress = runner.run()
    wall_s = time.monotonic() - started
    print(
        f"{progress.done + progress.failed} episodes ({progress.failed} failed) of 1 s sim on one warm stack "
        f"({args.renderer}, 96x72, noise {args.noise}) in {wall_s:.0f} s: {3600 * progress.done / wall_s:.0f} "
        "episodes/hour\n"
    )
    early_n, late_n = args.early, args.episodes
    early, late = marks[early_n], marks[late_n]
    if early is None or late is None:  # the matrix stopped short: a worker abandoned an episode or died
        missing = early_n if early is None else late_n
        print(f"soak: no measurement: the run ended before episode {missing}", file=sys.stderr)
        return 1
    print(f"| role | MB at episode {early_n} | MB at episode {late_n} | change | fds at {early_n} | fds at {late_n} |")
    print("|---|---|---|---|---|---|")
    for role in ["matrix driver", *ROLES]:
        if role not in early or role not in late:
            continue
        (pid_a, mb_a, fd_a), (pid_b, mb_b, fd_b) = early[role], late[role]
        same = "" if pid_a == pid_b else " (another process)"
        print(f"| {role}{same} | {mb_a:.1f} | {mb_b:.1f} | {mb_b - mb_a:+.1f} | {fd_a} | {fd_b} |")
    return 1 if progress.failed else 0


if __name__ == "__main__":
    sys.exit(main())
