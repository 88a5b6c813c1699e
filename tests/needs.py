"""A tool a test needs is missing: skip on a developer's machine, fail in CI (``CI=true``, set by ``.ci/run``).

A skipped test checks nothing, so CI, which has every tool (scripts/setup.sh installs what it can), must never pass
by skipping one.
"""

from __future__ import annotations

import importlib
import os

import pytest


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def missing(reason: str) -> None:
    """Skip the calling test for ``reason``, or fail it when running in CI."""
    if in_ci():
        pytest.fail(f"CI needs this test to run, but: {reason}")
    pytest.skip(reason)


def require(name: str):
    """``import name`` for a test that needs the module: skipped where it is not installed, a failure in CI (what
    ``pytest.importorskip`` would silently skip). Works at module level too."""
    try:
        return importlib.import_module(name)
    except ImportError as error:
        reason = f"{name} is not installed ({error})"
        if in_ci():
            pytest.fail(f"CI needs this test to run, but: {reason}", pytrace=False)
        pytest.skip(reason, allow_module_level=True)


def require_gl() -> None:
    """Skip (developer's machine) or fail (CI) unless the gl renderer can run here: moderngl and an EGL context."""
    require("moderngl")
    from services.simulator.gl_scene import egl_unavailable_reason

    if (reason := egl_unavailable_reason()) is not None:
        missing(f"no EGL context for the gl renderer: {reason}")


def require_bubblewrap() -> None:
    """Skip (developer's machine) or fail (CI) unless brain hosts can be sandboxed here (bubblewrap and util-linux's
    prlimit/setpriv, and namespaces it may create): ``orchestrator.stack.sandbox``."""
    from orchestrator.stack.sandbox import SandboxUnavailable, require_bubblewrap

    try:
        require_bubblewrap()
    except SandboxUnavailable as error:
        missing(str(error))
