"""The environment a test gives its child processes: the user's own ``DRIVEBENCH_*`` settings removed, so that a
variable left in a developer's shell cannot change what a test sees."""

from __future__ import annotations

import os
from collections.abc import Iterable


def clean_env(*, drop: Iterable[str] = (), **extra: str) -> dict[str, str]:
    """``os.environ`` without any ``DRIVEBENCH_*`` variable (nor the names in ``drop``), then ``extra`` on top."""
    dropped = set(drop)
    base = {k: v for k, v in os.environ.items() if not k.startswith("DRIVEBENCH_") and k not in dropped}
    return base | extra


def child_env(**extra: str) -> dict[str, str]:
    """:func:`clean_env` for a drivebench process started by the test: unbuffered output for its log, and the
    parent's pid, so a child left over by a failed test exits with us."""
    return clean_env(PYTHONUNBUFFERED="1", DRIVEBENCH_PARENT_PID=str(os.getpid())) | extra
