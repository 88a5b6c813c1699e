"""Waits on a condition with a deadline, never a fixed sleep before a positive assertion (CODE_STYLE.md, Tests)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
POLL_S = 0.05  # short next to any process start-up, long enough not to busy the two shared cores


def wait_for(
    condition: Callable[[], T], *, timeout_s: float, what: str, alive: Callable[[], str | None] = lambda: None
) -> T:
    """The first truthy value of ``condition()``; fails naming ``what`` after ``timeout_s``, or at once with the text
    ``alive()`` returns (say, a child's exit code and log tail) when something it depends on has died."""
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        assert (dead := alive()) is None, f"while waiting for {what}: {dead}"
        assert time.monotonic() < deadline, f"timed out after {timeout_s} s waiting for {what}"
        time.sleep(POLL_S)
    return value


def wait_for_file(
    path: Path, *, timeout_s: float, containing: str = "", alive: Callable[[], str | None] = lambda: None
) -> str:
    """The text of ``path`` once it exists (and holds ``containing``, when given)."""

    def text() -> str | None:
        if not path.exists():
            return None
        content = path.read_text(errors="replace")
        return content if containing in content else None

    return wait_for(
        text, timeout_s=timeout_s, what=f"{path}" + (f" to hold {containing!r}" if containing else ""), alive=alive
    )


def wait_for_subscribers(*publishers, timeout_s: float = 30.0) -> None:
    """Until every publisher has a matching subscriber (Zenoh's matching status: the subscriptions reached us)."""
    wait_for(
        lambda: all(publisher.has_subscribers() for publisher in publishers),
        timeout_s=timeout_s,
        what="subscribers on every publisher",
    )
