"""tests/needs.py: a test whose tool or module is missing skips on a developer's machine and fails in CI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent


@pytest.mark.parametrize("ci, outcome", [("", "1 skipped"), ("true", "1 error")], ids=["laptop", "ci"])
def test_a_missing_module_skips_on_a_laptop_and_fails_in_ci(tmp_path, ci, outcome):
    test = tmp_path / "test_uses_a_missing_module.py"
    test.write_text("from needs import require\n\nrequire('no_such_module_anywhere')\n\n\ndef test_x():\n    pass\n")
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test)],
        env=os.environ | {"CI": ci, "PYTHONPATH": str(TESTS)},
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert outcome in result.stdout, result.stdout
    if ci:
        assert "CI needs this test to run, but: no_such_module_anywhere is not installed" in result.stdout
