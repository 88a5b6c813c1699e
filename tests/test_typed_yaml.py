"""Typed YAML: process configs read from real files into msgspec types with constraints; every mistake is one line
``FILE:LINE: ...`` at the line that holds it (``command line: ...`` for an override)."""

from __future__ import annotations

import subprocess
import sys
from typing import Annotated

import msgspec
import pytest

from orchestrator.cli.errors import EXIT_USAGE
from orchestrator.matrix.load import MatrixError, load_matrix
from protocol.deploy.config import ConfigError, load_config
from protocol.deploy.typed_yaml import FileError, compose, convert, display
from services.scorer.service import ScorerConfig


class _Camera(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    width_px: Annotated[int, msgspec.Meta(ge=8, le=4096)] = 320
    name: Annotated[str, msgspec.Meta(pattern=r"^[a-z]+$")] = "front"


class _Config(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    run_id: Annotated[str, msgspec.Meta(min_length=1)] = "default"
    rate_hz: Annotated[float, msgspec.Meta(gt=0)] = 4.0
    cameras: Annotated[list[_Camera], msgspec.Meta(min_length=1)] = msgspec.field(default_factory=lambda: [_Camera()])


CONFIG_ERRORS = [
    # (file text, line, the whole message after "FILE:LINE: ")
    ("run_id: x\nrate_hz: fast\n", 2, "rate_hz must be a number, got 'fast'"),
    ("run_id: x\nrate: 2\n", 2, "unknown key 'rate' in the config (allowed: run_id, rate_hz, cameras)"),
    ("rate_hz: 0\n", 1, "rate_hz must be a number > 0.0, got 0"),
    ("cameras:\n  - width_px: 64\n  - width_px: 0\n", 3, "cameras[1].width_px must be an integer >= 8, got 0"),
    (
        "cameras:\n  - {width_px: 64}\n  - {heigth_px: 9}\n",
        3,
        "unknown key 'heigth_px' in cameras[1] (allowed: width_px, name)",
    ),
    ("cameras:\n\n  - name: Front\n", 3, "cameras[0].name must match the pattern '^[a-z]+$', got 'Front'"),
    ("cameras: []\n", 1, "cameras is empty (give at least one)"),
    ("run_id: ''\n", 1, "run_id must not be empty"),
    ("run_id: a\nrate_hz: 2\nrun_id: b\n", 3, "duplicate key 'run_id' (first on line 1)"),
    ("run_id: a\ncameras: [{width_px: 9}\n", 3, "invalid YAML: expected ',' or ']', but got '<stream end>'"),
    ("run_id: !!python/object:os.system ls\n", 1, "cannot read this value: could not determine a constructor"),
]


@pytest.mark.parametrize(("text", "line", "message"), CONFIG_ERRORS, ids=[f"{i}" for i in range(len(CONFIG_ERRORS))])
def test_config_mistakes_are_one_line_at_their_line(tmp_path, text, line, message):
    path = tmp_path / "service.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_config(_Config, path=path)
    assert str(caught.value).startswith(f"{path}:{line}: {message}"), str(caught.value)
    assert "\n" not in str(caught.value)


def test_overrides_are_named_as_the_command_line_with_their_key(tmp_path):
    path = tmp_path / "service.yaml"
    path.write_text("run_id: a\nrate_hz: 2\n")
    with pytest.raises(ConfigError, match=r"^command line: rate_hz must be a number > 0\.0, got -1$"):
        load_config(_Config, path=path, overrides=["rate_hz=-1"])
    with pytest.raises(ConfigError, match=r"^command line: cameras\[0\]\.width_px must be an integer >= 8, got 2$"):
        load_config(_Config, path=path, overrides=["cameras=[{width_px: 2}]"])
    # The file's own mistake keeps its line while an override sets another key.
    path.write_text("run_id: a\nrate_hz: slow\n")
    with pytest.raises(ConfigError, match=rf"^{path}:2: rate_hz must be a number, got 'slow'$"):
        load_config(_Config, path=path, overrides=["run_id=b"])


def test_a_valid_file_converts_with_defaults_and_merge_keys(tmp_path):
    path = tmp_path / "service.yaml"
    path.write_text("cameras:\n  - {width_px: 64}\n")
    assert load_config(_Config, path=path).cameras == [_Camera(width_px=64)]
    document = compose("a: &x {width_px: 9, name: b}\nb:\n  <<: *x\n  name: c\n", source="m.yaml")
    assert document.data["b"] == {"width_px": 9, "name": "c"}
    assert convert(document.data["b"], _Camera, document=document, path=("b",)) == _Camera(width_px=9, name="c")
    assert document.line(("b", "name")) == 4 and document.key_line(("b",)) == 2
    assert display(("brains", 1, "weights")) == "brains[1].weights"


def test_convert_names_the_path_below_where_the_data_sits():
    document = compose("x: 1\nb:\n  width_px: 4\n", source="m.yaml")
    with pytest.raises(FileError, match=r"^m\.yaml:3: b\.width_px must be an integer >= 8, got 4$"):
        convert(document.data["b"], _Camera, document=document, path=("b",))


def test_a_real_service_config_constraint_and_its_command_line(tmp_path):
    path = tmp_path / "scorer.yaml"
    path.write_text("run_id: r1\nlive_rate_hz: 0\n")
    with pytest.raises(ConfigError, match=rf"^{path}:2: live_rate_hz must be a number > 0\.0, got 0$"):
        load_config(ScorerConfig, path=path)
    done = subprocess.run(
        [sys.executable, "-m", "services.scorer", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [f"scorer: error: {path}:2: live_rate_hz must be a number > 0.0, got 0"]


# -- matrix files: the same typed reading, each mistake at its line ----------------------------------------------

MATRIX = "name: m\nbrains: [explicit]\ncircuits: [simple]\n"
MATRIX_ERRORS = [
    (MATRIX + "seed: seven\n", 4, "seed must be an integer, got 'seven'"),
    (MATRIX + "repetitions: yes\n", 4, "repetitions must be an integer, got true"),
    (MATRIX + "limits:\n  laps: 1\n  max_sim_secs: 9\n", 6, "unknown key 'max_sim_secs' in limits (allowed: laps, "),
    (MATRIX + "brains:\n  - explicit\n", 4, "duplicate key 'brains' (first on line 2)"),
    (MATRIX + "repetitions: 0\n", 4, "repetitions must be an integer >= 1, got 0"),
    (MATRIX + "limits:\n  laps: -1\n", 5, "limits.laps must be an integer >= 1, got -1"),
    (MATRIX + "camera:\n  height_px: 120\n  width_px: 0\n", 6, "camera.width_px must be an integer >= 8, got 0"),
    (
        MATRIX + "parts:\n  a:\n    repetitions: 2\n    limits: {step_s: 2}\n",
        7,
        "parts.a.limits.step_s must be a number <= 1.0",
    ),
    (MATRIX + "parts:\n  a:\n    circuits: [simple]\n    brains: [constant]\n", 7, "unknown key 'brains' in parts.a"),
    (MATRIX + "renderer: vulkan\n", 4, "renderer must be one of pybullet, gl, auto, got 'vulkan'"),
    (
        MATRIX + "shadows:\n  - name: constant\n    lable: slow\n",
        6,
        "unknown key 'lable' in shadows[0] (allowed: name,",
    ),
    (MATRIX + "camera:\n  near_m: 2\n  far_m: 1\n", 4, "need 0 < near_m < far_m, got 2.0 and 1.0 (at camera)"),
    (MATRIX + "limits: {laps: 1\n", 5, "invalid YAML:"),
]


@pytest.mark.parametrize(("text", "line", "message"), MATRIX_ERRORS, ids=[f"{i}" for i in range(len(MATRIX_ERRORS))])
def test_matrix_mistakes_are_one_line_at_their_line(tmp_path, text, line, message):
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(MatrixError) as caught:
        load_matrix(path)
    assert str(caught.value).startswith(f"{path}:{line}: {message}"), str(caught.value)
    assert "\n" not in str(caught.value) and caught.value.line == line


def test_drivebench_matrix_with_a_bad_file_is_a_usage_error_in_one_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(MATRIX + "limits:\n  laps: -1\n")
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "matrix", str(path), "--plan"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == EXIT_USAGE
    assert done.stdout == ""
    assert done.stderr.splitlines() == [f"drivebench: error: {path}:5: limits.laps must be an integer >= 1, got -1"]
