"""Check MCAP files with the independent Node validator in tools/mcap-validate (built on the official TypeScript
MCAP reader, the code Foxglove/Lichtblick open files with), so tests do not only trust our own Python reader.

    from mcap_validation import assert_valid_mcap
    assert_valid_mcap(run_dir / "run.mcap")   # skips the test when node / node_modules are missing
"""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from needs import missing

from protocol import environment

VALIDATOR_DIR = Path(__file__).resolve().parent.parent / "tools" / "mcap-validate"
_SCRIPT = VALIDATOR_DIR / "validate.mjs"
_TIMEOUT_S = 120
SKIP_REASON = "node / @mcap validator not installed: run scripts/setup.sh"


@dataclass(frozen=True)
class FileResult:
    """One file's verdict, as the validator's ``--json`` line reports it."""

    file: str
    ok: bool
    truncated: bool
    messages: int
    channels: int
    errors: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ValidationResult:
    """The validator's exit code (0 ok, 1 invalid, 2 truncated only) and one result per file, in argument order."""

    returncode: int
    files: list[FileResult]

    @property
    def ok(self) -> bool:
        return self.returncode == 0 and all(f.ok for f in self.files)

    def describe(self) -> str:
        """One line per bad file, for assertion messages."""
        return "\n".join(f"{f.file}: {'; '.join(f.errors)}" for f in self.files if not f.ok)


def validator_available() -> bool:
    """True when node is on PATH and ``npm ci`` has installed the validator's dependencies."""
    return shutil.which("node") is not None and (VALIDATOR_DIR / "node_modules" / "@mcap" / "core").is_dir()


def validate_mcap(*paths: str | Path, decode: bool = True, require_viewable: bool = True) -> ValidationResult:
    """Run the validator on ``paths`` and parse its per-file JSON lines.

    Raises RuntimeError when the validator itself fails (bad install, usage error): that must not read as
    "the file is invalid", or a broken tool would make every test look like a recording bug.
    """
    if not paths:
        raise ValueError("validate_mcap needs at least one path")
    command = ["node", str(_SCRIPT), "--json"]
    command += ["--decode"] if decode else []
    command += ["--require-viewable"] if require_viewable else []
    command += [str(p) for p in paths]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=_TIMEOUT_S, check=False)
    try:
        files = [FileResult(**json.loads(line)) for line in proc.stdout.splitlines() if line.strip()]
    except (json.JSONDecodeError, TypeError) as exc:
        raise RuntimeError(f"unparseable validator output ({exc}): {proc.stdout!r} {proc.stderr!r}") from exc
    if len(files) != len(paths):
        raise RuntimeError(
            f"validator exited {proc.returncode} with {len(files)} results for {len(paths)} files: "
            f"{proc.stderr.strip()}"
        )
    return ValidationResult(returncode=proc.returncode, files=files)


def assert_valid_mcap(*paths: str | Path, **kwargs: bool) -> ValidationResult:
    """Assert every file passes the validator (decode and viewability on by default).

    Without Node the check is skipped; but where Node is there (``scripts/test.sh`` then sets
    ``DRIVEBENCH_REQUIRE_MCAP_VALIDATOR=1``) a missing validator is a broken set-up and fails, never a silent skip.
    """
    if not validator_available():
        if environment.REQUIRE_MCAP_VALIDATOR.value() == "1":
            pytest.fail(f"the MCAP validator is not installed although Node is: {SKIP_REASON}")
        missing(SKIP_REASON)
    result = validate_mcap(*paths, **kwargs)
    assert result.ok, f"MCAP validator (exit {result.returncode}):\n{result.describe()}"
    return result
