"""How brains are named (registry), the Behavior Metrics adapter, and the wire contract's JSON Schemas."""

from __future__ import annotations

import base64
import json
import math
import os
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
from needs import require

from brains.base import GroundTruth, Observation
from brains.behavior_metrics.adapter import BM_DEFAULT_CONFIG, BehaviorMetricsBrain, BrainExecuteError
from brains.behavior_metrics.interfaces import TRANSFORM_OPTIONS, NoSuchSensor
from brains.registry import (
    BrainOptionsError,
    UnknownBrainError,
    brain_sources,
    bus_name,
    make_brain,
    preflight,
    resolve,
)
from protocol import codec
from protocol.messages import CameraFrame, Command, Header
from protocol.schema import BRAIN_MESSAGES, message_schema, schema_files

ROOT = Path(__file__).resolve().parent.parent
BM_EXAMPLE = ROOT / "examples" / "behavior_metrics" / "brain_f1_follow_line.py"


# -- names -----------------------------------------------------------------------------------------------------------


def test_a_name_resolves_to_built_in_module_path_or_brain_file():
    assert resolve("explicit").origin == "built-in"
    assert resolve("my_pkg.brains:Fast").target == "my_pkg.brains:Fast"
    assert resolve("my_pkg.brains:Fast").origin == "module path"
    source = resolve(str(BM_EXAMPLE))
    assert source.origin == "Behavior Metrics file" and dict(source.options) == {"file": str(BM_EXAMPLE)}
    for bad in ("my pkg:Brain", ":Brain", "pkg:", "pkg:1x"):
        with pytest.raises(UnknownBrainError):
            resolve(bad)


def test_bus_names_are_key_safe():
    assert bus_name("explicit") == "explicit"
    assert bus_name("my_pkg.brains:Fast") == "Fast"
    assert bus_name("my_pkg.brains:Outer.Inner") == "Outer-Inner"
    assert bus_name("some/where/brain_f1.py") == "brain_f1"


def test_installed_entry_points_are_listed_with_their_package():
    sources = {source.name: source for source in brain_sources()}
    assert sources["explicit"].origin == "built-in"
    assert sources["my_brain"].origin.startswith("entry point of drivebench-my-brain"), "run scripts/setup.sh"
    assert type(make_brain("my_brain")).__name__ == "MyBrain"


# -- the Behavior Metrics adapter ------------------------------------------------------------------------------------

BM_STYLE = """
import numpy as np


class Brain:
    instances = 0

    def __init__(self, sensors, actuators, model=None, handler=None, config=None):
        Brain.instances += 1
        self.camera = sensors.get_camera("camera_0")
        self.motors = actuators.get_motor("motors_0")
        self.handler, self.model, self.config = handler, model, config
        self.frames = 0

    def execute(self):
        image = self.camera.getImage().data
        self.frames += 1
        self.handler.update_frame("frame_0", image)
        self.motors.sendV(float(image[0, 0, 0]))  # red of the first pixel: BM's frames are RGB
        if self.frames == 1:
            self.motors.sendW(np.random.uniform(-1, 1))  # later frames leave W as it was
"""
FIXTURES = ROOT / "tests" / "fixtures" / "behavior_metrics"


@pytest.fixture
def bm_file(tmp_path):
    path = tmp_path / "brain_bm_style.py"
    path.write_text(BM_STYLE)
    return path


def observation(rgb: tuple[int, int, int], seq: int = 0, truth: GroundTruth | None = None) -> Observation:
    image = np.zeros((4, 6, 3), np.uint8)
    image[...] = rgb
    image.flags.writeable = False
    return Observation(image_rgb=image, stamp_ns=seq * 50_000_000, seq=seq, ground_truth=truth)


def test_behavior_metrics_brain_is_built_with_keywords_and_sees_rgb(bm_file):
    brain = BehaviorMetricsBrain(file=str(bm_file), model="weights.h5", config={"k": 1})
    brain.reset(seed=5)
    first = brain.act(observation((10, 20, 30)))
    assert first.speed_mps == 10.0  # image[0, 0, 0] of an RGB frame is the red value
    second = brain.act(observation((40, 20, 30), seq=1))
    assert second.speed_mps == 40.0 and second.yaw_rate_radps == first.yaw_rate_radps  # motors keep the last W
    # (sensors, actuators, model=None, handler=None, config=None): by keyword, each lands where it belongs
    assert brain._brain.model == "weights.h5" and brain._brain.handler is brain.handler
    assert brain._brain.config == {**BM_DEFAULT_CONFIG, "k": 1}  # BM's keys are always there
    assert list(brain.debug_images) == ["frame_0"] and brain.debug_images["frame_0"][0, 0, 0] == 40
    brain.reset(seed=5)
    assert brain._brain.frames == 0 and brain.debug_images == {}  # a new Brain: nothing carried over
    assert brain.act(observation((10, 20, 30))) == first  # seeded: numpy's global generator from reset's seed
    assert not brain.needs_ground_truth  # it never reads the pose: its host does not wait for one


def test_config_comes_from_bm_defaults_then_a_bm_config_file_then_the_option(tmp_path, bm_file):
    config_file = tmp_path / "bm.yml"
    config_file.write_text(
        "Behaviors:\n  Robot:\n    Parameters:\n      Model: net.pth\n      GPU: false\n      ImageTranform: rain\n"
    )
    brain = BehaviorMetricsBrain(file=str(bm_file), config_file=str(config_file), config={"ImageTranform": "fog"})
    assert brain._brain.config == {**BM_DEFAULT_CONFIG, "GPU": False, "ImageTranform": "fog"}
    assert brain._brain.model == "net.pth"  # the file's Model, passed as model= as BM does
    no_model = BehaviorMetricsBrain(file=str(bm_file), model="")
    assert no_model._brain.model is None  # BM passes model= only when one is set


def test_transform_image_is_bm_perturbation_seeded_by_the_episode(bm_file):
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")  # no network check at import
    require("albumentations")
    brain = BehaviorMetricsBrain(file=str(bm_file))
    image = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    assert brain.handler.transform_image(image, "") is image
    night = brain.handler.transform_image(np.full((8, 8, 3), 200, np.uint8), "night")
    assert int(night[0, 0, 0]) in (72, 73)  # brightness -0.5 of the full range: 200 - 127.5
    brain.reset(seed=3)
    first = [brain.handler.transform_image(image, option) for option in TRANSFORM_OPTIONS[1:]]
    brain.reset(seed=3)
    again = [brain.handler.transform_image(image, option) for option in TRANSFORM_OPTIONS[1:]]
    for option, a, b in zip(TRANSFORM_OPTIONS[1:], first, again, strict=True):
        assert a.shape == image.shape and a.dtype == np.uint8 and not np.array_equal(a, image), option
        assert np.array_equal(a, b), f"{option}: same seed, same frames, different output"
    with pytest.raises(ValueError, match="unknown option 'hail'"):
        brain.handler.transform_image(image, "hail")


def test_the_pose_is_the_frames_ground_truth_in_bm_conventions_and_there_is_no_laser(bm_checkout):
    brain = BehaviorMetricsBrain(file=str(bm_checkout / "behavior_metrics/brains/gazebo/f1/brain_f1_keywords.py"))
    assert brain.needs_ground_truth  # it reads get_pose3d: its host hands it the pose of every frame
    brain.act(observation((0, 0, 0), truth=GroundTruth(x_m=3.0, y_m=-4.0, yaw_rad=math.pi / 2, circuit="simple")))
    pose = brain.pose3d.getPose3d()
    assert (pose.x, pose.y, pose.z, pose.yaw, pose.pitch, pose.roll) == (3.0, -4.0, 0.0, math.pi / 2, 0.0, 0.0)
    assert pose.q == pytest.approx([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])  # [w, x, y, z]
    assert brain.handler.reported_pose is pose  # handler.update_pose3d
    with pytest.raises(NoSuchSensor, match=r"get_laser\('laser_0'\): Behavior Metrics' F1 car has no laser"):
        brain.sensors.get_laser("laser_0")
    brain.reset(seed=0)  # no pose fed for 21 frames of driving: the brain's own check fails, naming where
    with pytest.raises(
        BrainExecuteError, match=r"brain_f1_keywords.py:\d+: execute\(\) raised RuntimeError: pose3d_0 has not moved"
    ):
        for seq in range(25):
            brain.act(observation((0, 0, 0), seq=seq))


def test_a_file_importing_bm_modules_needs_the_checkout_and_then_imports_them(bm_checkout, monkeypatch):
    monkeypatch.delenv("DRIVEBENCH_BM_ROOT", raising=False)
    file = bm_checkout / "behavior_metrics/brains/gazebo/f1/brain_f1_fake_net.py"
    with pytest.raises(BrainOptionsError) as refused:
        preflight(str(file), {"model": "gains.json"})
    assert str(file) in str(refused.value) and "from utils.constants import" in str(refused.value)
    assert "bm_root=PATH" in str(refused.value) and "DRIVEBENCH_BM_ROOT" in str(refused.value)
    monkeypatch.setenv("DRIVEBENCH_BM_ROOT", str(bm_checkout))  # the repository's root: its behavior_metrics is found
    preflight(str(file), {"model": "gains.json"})
    brain = make_brain(str(file), model="gains.json", bm_root=str(bm_checkout / "behavior_metrics"))
    image = np.zeros((40, 60, 3), np.uint8)
    image[20:, 10:14] = (255, 0, 0)  # the red line left of the centre: turn left
    action = brain.act(Observation(image_rgb=image, stamp_ns=0, seq=0))
    assert action.speed_mps == 5.0 and action.yaw_rate_radps > 0  # gains.json's speed, from the checkout's models
    import brains.base

    assert Path(brains.base.__file__).parent == ROOT / "brains"  # drivebench's own modules are untouched
    with pytest.raises(BrainOptionsError, match="not a Behavior Metrics checkout"):
        make_brain(str(file), model="gains.json", bm_root=str(bm_checkout / "nowhere"))


def test_behavior_metrics_brain_file_mistakes_are_one_line(tmp_path, bm_file):
    missing = tmp_path / "none.py"
    with pytest.raises(BrainOptionsError, match="not found"):
        BehaviorMetricsBrain(file=str(missing))
    (tmp_path / "no_class.py").write_text("x = 1\n")
    with pytest.raises(BrainOptionsError, match="defines no class Brain"):
        BehaviorMetricsBrain(file=str(tmp_path / "no_class.py"))
    (tmp_path / "broken.py").write_text("import no_such_module_here\n")
    with pytest.raises(BrainOptionsError, match="failed to import at line 1: ModuleNotFoundError"):
        BehaviorMetricsBrain(file=str(tmp_path / "broken.py"))
    (tmp_path / "old.py").write_text("class Brain:\n    def __init__(self, sensors):\n        pass\n")
    with pytest.raises(BrainOptionsError, match=r"does not take Brain\(sensors, actuators, handler=..., config=...\)"):
        BehaviorMetricsBrain(file=str(tmp_path / "old.py"))
    (tmp_path / "needy.py").write_text(
        "class Brain:\n    def __init__(self, sensors, actuators, handler=None, config=None):\n"
        "        self.gain = config['SteeringGain']\n"
    )
    with pytest.raises(BrainOptionsError, match=r"needy.py:3\): missing config key 'SteeringGain'"):
        BehaviorMetricsBrain(file=str(tmp_path / "needy.py"))
    with pytest.raises(BrainOptionsError, match=r"brain_bm_style.py': unknown ImageTranform 'hail'"):
        preflight(str(bm_file), {"config": {"ImageTranform": "hail"}})


def test_the_shipped_behavior_metrics_example_is_found_by_its_path():
    brain = make_brain(str(BM_EXAMPLE))
    assert isinstance(brain, BehaviorMetricsBrain)
    assert make_brain("behavior_metrics", file=str(BM_EXAMPLE)).file == str(BM_EXAMPLE)


# -- the wire contract -----------------------------------------------------------------------------------------------


def test_committed_schemas_are_the_generated_ones():
    folder = ROOT / "docs" / "protocol"
    for name, text in schema_files().items():
        assert (folder / name).read_text() == text, f"docs/protocol/{name} is stale: run drivebench brains schema"
    assert {p.name for p in folder.glob("*.schema.json")} == set(schema_files())


def as_json_value(value):
    """A MessagePack-decoded value as JSON Schema sees it (bin -> base64 text, as the schema's JSON form)."""
    if isinstance(value, bytes):
        return base64.b64encode(value).decode()
    if isinstance(value, dict):
        return {key: as_json_value(item) for key, item in value.items()}
    if isinstance(value, list):
        return [as_json_value(item) for item in value]
    return value


def test_real_messages_on_the_wire_validate_against_their_schema():
    jsonschema = require("jsonschema")
    header = Header(run_id="r", episode=0, seq=3, stamp_ns=150_000_000)
    frame = CameraFrame(header=header, width_px=2, height_px=1, data=bytes(6))
    command = Command(header=header, brain="mine", frame_seq=3, speed_mps=5.0, yaw_rate_radps=-0.2)
    for message in (frame, command):
        wire = msgpack.unpackb(codec.encode(message))  # what a non-Python brain decodes: a map with "type"
        assert wire["type"] == f"drivebench.{type(message).__name__}.v1"
        jsonschema.validate(as_json_value(wire), message_schema(type(message)))
    # And what such a brain sends back decodes as the project's own type.
    reply = {
        "type": "drivebench.Command.v1",
        "header": {"run_id": "r", "episode": 0, "seq": 0, "stamp_ns": 0},
        "brain": "mine",
        "frame_seq": 0,
        "speed_mps": 4.0,
        "yaw_rate_radps": 0.1,
    }
    jsonschema.validate(reply, message_schema(Command))
    assert codec.decode(msgpack.packb(reply), Command).speed_mps == 4.0
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**reply, "speed_mps": "fast"}, message_schema(Command))
    assert (
        json.loads(schema_files()["CameraFrame.schema.json"])["$defs"]["CameraFrame"]["properties"]["data"]["x-msgpack"]
        == "bin"
    )
    assert len(BRAIN_MESSAGES) == len(schema_files())


def test_schema_command_writes_the_folder(tmp_path):
    import subprocess

    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "brains", "schema", "-o", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(schema_files())


# -- matrix files and the command line -------------------------------------------------------------------------------


def test_matrix_files_name_brains_by_module_path_and_brain_file(tmp_path, bm_file):
    from orchestrator.matrix.load import MatrixError, load_matrix

    (tmp_path / "lap_module.py").write_text("class Mine:\n    pass\n")
    sys.path.insert(0, str(tmp_path))
    try:
        path = tmp_path / "m.yaml"
        path.write_text("name: mine\nbrains: [lap_module:Mine, brain_bm_style.py]\ncircuits: [simple]\n")
        matrix = load_matrix(path)
        assert [(b.label, b.brain) for b in matrix.brains] == [
            ("Mine", "lap_module:Mine"),
            ("brain_bm_style", str(bm_file)),
        ]
        path.write_text("name: mine\nbrains: [lap_module:Missing]\ncircuits: [simple]\n")
        with pytest.raises(MatrixError, match=r"m.yaml:2: brain 'lap_module:Missing': module 'lap_module' has no"):
            load_matrix(path)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("lap_module", None)


def test_brains_check_command_exit_codes_and_fix_lines(tmp_path):
    import subprocess

    (tmp_path / "kmh.py").write_text(
        "from brains.base import Action\nclass Kmh:\n    def reset(self, *, seed):\n"
        "        pass\n    def act(self, observation):\n"
        "        return Action(speed_mps=72.0, yaw_rate_radps=0.0)\n"
    )

    def check(*args):
        return subprocess.run(
            [sys.executable, "-m", "orchestrator.cli", "brains", "check", *args, "--memory-steps", "40"],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=tmp_path,
        )

    good = check("constant", "--brain-option", "speed_mps=3")
    assert good.returncode == 0 and good.stdout.count("PASS") == 8, good.stdout + good.stderr
    bad = check("kmh:Kmh")
    assert bad.returncode == 1 and "FAIL  units" in bad.stdout and "fix: speed_mps is metres per second" in bad.stdout
    typo = check("--brain-option", "oops", "explicit")
    assert typo.returncode == 2 and "Traceback" not in typo.stderr and "--brain-option" in typo.stderr
