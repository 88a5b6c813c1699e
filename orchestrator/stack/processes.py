"""The one process supervisor: how drivebench starts, watches and stops the processes of a stack.

Both the launcher (a whole local stack) and ``drivebench swap`` (one brain host added to a running stack) start
their children here: each in its own session (Ctrl-C reaches only the parent, which stops children in order), stdin
closed, stdout and stderr appended to one log file, Python unbuffered so that the log's last line is the latest.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

log = logging.getLogger("drivebench.processes")

LOG_LINE_CHARS = 200  # a dead process's last log line, quoted in its failure (a simulator's may hold a whole spec)


def python_module(module: str) -> list[str]:
    """The command line that runs ``python -m module`` for a child process, in Python's safe-path mode (``-P``).

    Without ``-P`` the current folder comes first on ``sys.path``, so a user's own ``circuits/`` or ``brains/``
    folder (imported circuits, a Behavior Metrics checkout) would shadow drivebench's packages and the child would
    die at import. ``module:Class`` brains still resolve from the current folder: the brain registry appends it to
    ``sys.path`` after drivebench's packages."""
    return [sys.executable, "-P", "-m", module]


def spawn(
    argv: Sequence[str], *, log_path: Path, env: Mapping[str, str], process_group: int | None = None
) -> subprocess.Popen:
    """Start ``argv`` with its output appended to ``log_path``: in its own session, or with ``process_group`` in
    that process group (0: a new one led by this process; a Ray episode kills its whole stack as one group)."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    group: dict = {"start_new_session": True} if process_group is None else {"process_group": process_group}
    with open(log_path, "ab") as log_file:
        return subprocess.Popen(
            list(argv),
            stdout=log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**env, "PYTHONUNBUFFERED": "1"},
            **group,
        )


def last_log_line(log_path: Path) -> str:
    """The last non-blank line of a log ("" when there is none), cut to :data:`LOG_LINE_CHARS`."""
    try:
        lines = [line for line in log_path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    line = lines[-1] if lines else ""
    return line[: LOG_LINE_CHARS - 3] + "..." if len(line) > LOG_LINE_CHARS else line


def describe_exit(code: int) -> str:
    """``exited with code 3`` or, for a process a signal ended, ``killed by SIGKILL``."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def exit_reason(process: subprocess.Popen, *, what: str, log_path: Path) -> str | None:
    """Why ``process`` is gone (``<what> exited with code 1; its last log line: ...``), or None while it runs."""
    code = process.poll()
    if code is None:
        return None
    detail = last_log_line(log_path)
    return f"{what} {describe_exit(code)}" + (f"; its last log line: {detail}" if detail else "")


def stop(processes: Sequence[subprocess.Popen], *, grace_s: float, names: Sequence[str] = ()) -> None:
    """SIGTERM every process still running, wait up to ``grace_s`` in all, then SIGKILL what is left (logged with
    its name from ``names``, when given)."""
    import time

    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for index, process in enumerate(processes):
        try:
            process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            name = names[index] if index < len(names) else f"pid {process.pid}"
            log.warning("%s did not stop in %.0f s: killing it", name, grace_s)
            process.kill()
            process.wait()
