"""The scene options (``--camera``, ``--renderer``, ``--variation``) read the same in every command's ``--help``
(``drivebench run``, ``drivebench dataset collect``, ``drivebench matrix``): one help text, declared once
(``orchestrator.cli.run.add_scene_options``); only the default, which differs by command, differs, and it is stated."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

COMMANDS = {"run": ("run",), "collect": ("dataset", "collect"), "matrix": ("matrix",)}
SCENE_OPTIONS = ("--camera", "--renderer", "--variation")
# The defaults each command states; they differ on purpose (run renders with the reference renderer, batch commands
# take the faster one where it works) and stay as they were.
RENDERER_DEFAULTS = {
    "run": "$DRIVEBENCH_RENDERER, else pybullet",
    "collect": "$DRIVEBENCH_RENDERER, else auto",
    "matrix": "the file's `renderer:`, else $DRIVEBENCH_RENDERER, else auto",
}


def help_of(command: str) -> dict[str, str]:
    """Each option's help text, whitespace joined, from ``drivebench COMMAND --help`` as a user sees it."""
    env = dict(os.environ, COLUMNS="100")
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *COMMANDS[command], "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert done.returncode == 0, done.stderr
    options = {}
    for block in re.split(r"\n(?=  -)", done.stdout):
        words = block.split()
        if words and words[0].startswith("--"):
            options[words[0].rstrip(",")] = " ".join(words)
    return options


@pytest.fixture(scope="module")
def helps() -> dict[str, dict[str, str]]:
    return {command: help_of(command) for command in COMMANDS}


def test_run_and_collect_take_every_scene_option_and_matrix_the_renderer(helps):
    for command in ("run", "collect"):
        assert set(SCENE_OPTIONS) <= set(helps[command]), command
    assert "--renderer" in helps["matrix"]


@pytest.mark.parametrize("option", SCENE_OPTIONS)
def test_each_scene_option_has_one_help_text_less_its_default(helps, option):
    texts = {}
    for command, options in helps.items():
        if option in options:
            texts[command] = options[option].split("default:")[0]
    assert len(texts) >= 2
    assert len(set(texts.values())) == 1, texts


@pytest.mark.parametrize("command", list(COMMANDS))
def test_each_command_states_its_renderer_default(helps, command):
    # ... and the look that needs gl says what it picks (look=gazebo: auto)
    assert helps[command]["--renderer"].endswith(f"default: {RENDERER_DEFAULTS[command]} (look=gazebo: auto)")
