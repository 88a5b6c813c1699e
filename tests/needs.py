"""A tool a test needs is missing: skip on a developer's machine, fail in CI (``CI=true``, set by ``.ci/run``).

A skipped test checks nothing, so CI, which has every tool (scripts/setup.sh installs what it can), must never pass
by skipping one.
"""

from __future__ import annotations

import os

import pytest


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def missing(reason: str) -> None:
    """Skip the calling test for ``reason``, or fail it when running in CI."""
    if in_ci():
        pytest.fail(f"CI needs this test to run, but: {reason}")
    pytest.skip(reason)
