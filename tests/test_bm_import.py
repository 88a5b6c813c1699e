"""Behavior Metrics experiment configs as drivebench matrices (``drivebench bm import``), and BM brains in them
through the real stack. The configs and brains are written for these tests in BM's shape (tests/fixtures/
behavior_metrics), never copied from BM."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from orchestrator.matrix.bm_config import BM_WORLDS, BMConfigError, convert_bm_config, world_of
from orchestrator.matrix.load import load_matrix
from orchestrator.matrix.results import ResultStore

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "tests" / "fixtures" / "behavior_metrics"
CONFIG = FIXTURES / "multi_brain_multi_world.yml"


def drivebench(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True, timeout=timeout_s
    )


def test_every_bm_world_name_maps_to_a_circuit_and_variation():
    assert world_of("/opt/jderobot/share/jderobot/gazebo/launch/simple_circuit.launch") == (
        "simple_circuit",
        "simple",
        {},
    )
    assert world_of("montmelo_white_road_no_red_line.launch") == (
        "montmelo_white_road_no_red_line",
        "montmelo",
        {"road": "white", "line": "none"},
    )
    assert world_of("many_curves_no_red_line_no_wall") == (
        "many_curves_no_red_line_no_wall",
        "many_curves",
        {"line": "none", "walls": "off"},
    )
    assert world_of("nurburgring_line_no_wall.launch")[1:] == ("nurburgring", {"walls": "off"})
    assert len([name for name in BM_WORLDS if name.startswith("simple_circuit")]) == 9  # BM's nine variants
    with pytest.raises(
        BMConfigError, match=r"unknown Behavior Metrics world 'many_curves_white_line.launch' \(known: "
    ):
        world_of("many_curves_white_line.launch")  # the docs claim it; BM ships none


def test_a_multi_brain_multi_world_config_converts_to_a_matrix_that_loads(bm_checkout, tmp_path):
    out = tmp_path / "bm.yaml"
    conversion = convert_bm_config(
        yaml.safe_load(CONFIG.read_text()),
        config_path=CONFIG,
        out_path=out,
        bm_root=bm_checkout / "behavior_metrics",
        bm_root_option=str(bm_checkout),
    )
    out.write_text(conversion.text(source=str(CONFIG)))
    matrix = load_matrix(out)
    assert [brain.label for brain in matrix.brains] == ["brain_f1_fake_net", "brain_f1_keywords", "brain_f1_fails"]
    fake_net = dict(matrix.brains[0].options)
    assert fake_net["model"] == "gains.json" and fake_net["bm_root"] == str(bm_checkout)
    assert fake_net["config"] == {"ImageCropped": True, "GPU": False, "ImageTranform": ""}  # moved to the matrix
    assert "model" not in dict(matrix.brains[1].options)  # Model '' is no model, as in BM
    episodes = {(e.brain.label, e.spec.circuit, e.spec.world.walls, e.spec.max_sim_seconds) for e in matrix.episodes}
    assert episodes == {
        (brain, circuit, walls, timeout)
        for brain in ("brain_f1_fake_net", "brain_f1_keywords", "brain_f1_fails")
        for circuit, walls, timeout in (("simple", True, 60.0), ("many_curves", False, 90.0))
    }
    assert {e.spec.camera.width_px for e in matrix.episodes} == {640}
    assert all([type(stage).__name__ for stage in e.spec.noise] == ["Night"] for e in matrix.episodes)
    dropped = [line.split(":")[0] for line in conversion.dropped]
    assert dropped == [
        "Behaviors.Robot.Sensors",
        "Behaviors.Robot.Actuators",
        "Behaviors.Simulation.RealTimeUpdateRate",
        "Behaviors.Dataset",
        "Behaviors.Stats",
        "Behaviors.Layout",
    ]  # each once, the outermost key only
    assert all(f"# dropped: {line}" in out.read_text() for line in conversion.dropped)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda b: b["Simulation"].update(World="hockenheim.launch"), "unknown Behavior Metrics world 'hockenheim"),
        (lambda b: b["Experiment"].update(Timeout=[1, 2, 3]), "Experiment.Timeout has 3 entries for 2 worlds"),
        (lambda b: b["Robot"].update(Type="drone"), "drivebench runs Behavior Metrics' F1 car only"),
        (lambda b: b["Robot"]["Parameters"].update(Model=["a", "b"]), "Parameters.Model has 2 entries for 3 brains"),
        (
            lambda b: b["Robot"].update(BrainPath="brains/gazebo/f1/nope.py"),
            "brain file 'brains/gazebo/f1/nope.py' not found",
        ),
    ],
)
def test_a_config_drivebench_cannot_convert_is_one_line_naming_the_key(bm_checkout, tmp_path, edit, message):
    data = yaml.safe_load(CONFIG.read_text())
    edit(data["Behaviors"])
    with pytest.raises(BMConfigError, match=message):
        convert_bm_config(
            data, config_path=CONFIG, out_path=tmp_path / "m.yaml", bm_root=bm_checkout / "behavior_metrics"
        )


def test_without_a_timeout_each_world_gets_bm_s_default_reference_lap_times_1_1(bm_checkout, tmp_path):
    data = yaml.safe_load(CONFIG.read_text())
    del data["Behaviors"]["Experiment"]["Timeout"]
    parts = convert_bm_config(
        data, config_path=CONFIG, out_path=tmp_path / "m.yaml", bm_root=bm_checkout / "behavior_metrics"
    ).matrix["parts"]
    assert [part["limits"]["max_sim_seconds"] for part in parts.values()] == [82.5, 166.1]  # 75 s and 151 s x 1.1


def test_bad_input_is_one_line_and_exit_2_before_anything_starts(bm_checkout, tmp_path):
    bad = tmp_path / "bad.yml"
    bad.write_text(CONFIG.read_text().replace("many_curves_no_wall.launch", "many_curves_night.launch"))
    run = drivebench("bm", "import", str(bad), "-o", str(tmp_path / "m.yaml"), "--bm-root", str(bm_checkout))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "unknown Behavior Metrics world" in run.stderr and "simple_circuit_white_line" in run.stderr
    assert not (tmp_path / "m.yaml").exists()
    raising = tmp_path / "brain_f1_raises.py"
    raising.write_text(
        "class Brain:\n    def __init__(self, sensors, actuators, handler=None, config=None):\n"
        "        raise RuntimeError('no camera calibration')\n"
    )
    run = drivebench("run", "--brain", str(raising), "--out", str(tmp_path / "run"))
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert str(raising) in run.stderr and "brain_f1_raises.py:3): RuntimeError: no camera calibration" in run.stderr
    fake_net = bm_checkout / "behavior_metrics/brains/gazebo/f1/brain_f1_fake_net.py"
    run = drivebench(
        "run", "--brain", str(fake_net), "--brain-option", "model=gains.json", "--out", str(tmp_path / "r")
    )
    assert run.returncode == 2 and "bm_root=PATH" in run.stderr and "from utils.constants import" in run.stderr
    assert not (tmp_path / "r" / "launcher.log").exists()  # refused before the stack


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(900)  # six episodes at 640x480 (smoke keeps a BM brain file's camera): 56 s here, 2 cores
def test_a_converted_bm_config_runs_as_a_smoke_matrix_each_brain_as_its_code_says(bm_checkout, tmp_path):
    out = tmp_path / "bm.yaml"
    converted = drivebench("bm", "import", str(CONFIG), "-o", str(out), "--bm-root", str(bm_checkout))
    assert converted.returncode == 0, converted.stderr
    assert converted.stderr.count("not converted: Behaviors.Layout") == 1
    run = drivebench("matrix", str(out), "--smoke", "-o", str(tmp_path / "runs"), "--workers", "1", timeout_s=600)
    assert run.returncode == 3, run.stderr  # the matrix ran; the failing brain's episodes failed
    with ResultStore(tmp_path / "runs", create=False) as store:
        results = store.results()
    by_brain: dict[str, list] = {}
    for result in results:
        by_brain.setdefault(result.brain, []).append(result)
        assert result.perturbation == "night"
    for brain in ("brain_f1_fake_net", "brain_f1_keywords"):  # imports from the checkout; keywords, pose, config
        assert [r.status for r in by_brain[brain]] == ["done", "done"], [r.failure for r in by_brain[brain]]
        assert all(r.score.metrics.completed_distance_m > 5.0 for r in by_brain[brain])  # it drove, in both worlds
    for failed in by_brain["brain_f1_fails"]:
        assert failed.status == "failed" and failed.failure_kind == "brain_died", failed.failure
        assert "brain_f1_fails.py:15: execute() raised KeyError: 'SteeringGain'" in failed.failure.detail
    assert "night" in (tmp_path / "runs" / "report.md").read_text()


def test_bm_perturbations_are_matrix_perturbations_with_their_names_as_labels(tmp_path):
    path = tmp_path / "robust.yaml"
    path.write_text("brains: [explicit]\ncircuits: [simple]\nperturbations: [none, rain, fog, night+affine]\n")
    matrix = load_matrix(path)
    assert [e.perturbation for e in matrix.episodes] == ["none", "rain", "fog", "night+affine"]
    assert [[type(s).__name__ for s in e.spec.noise] for e in matrix.episodes] == [
        [],
        ["Rain"],
        ["Fog"],
        ["Night", "Affine"],
    ]
    path.write_text("brains: [explicit]\ncircuits: [simple]\nperturbations: [rain=3]\n")
    with pytest.raises(ValueError, match="robust.yaml:3: .*noise model rain takes no value"):
        load_matrix(path)


@pytest.mark.slow
@pytest.mark.integration
def test_a_bm_brain_calling_every_transform_drives_under_bm_rain_through_the_real_stack(tmp_path):
    """The brain host applies each of BM's perturbations through transform_image (the brain raises if one leaves its
    frame as it was or changes its shape), while the noise injector rains on the frames it gets."""

    score = two_seconds_at_160x120(
        tmp_path, "--brain", str(FIXTURES / "brain_f1_every_transform.py"), "--noise", "rain"
    )
    assert score["reason"] == "time_limit" and score["metrics"]["steps"] == 40, score  # no frame raised
    assert score["spec"]["noise"] == [{"model": "rain"}]
    assert score["metrics"]["completed_distance_m"] == pytest.approx(6.0, abs=0.2)  # 3 m/s for 2 s


@pytest.fixture
def bm_imports_undone(monkeypatch):
    """Undo what importing a BM file with a checkout does to this process (a brain host has one for life): the
    checkout on sys.path and on drivebench's brains package path, BM's modules imported from it."""
    import brains

    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(brains, "__path__", list(brains.__path__))
    before = set(sys.modules)
    yield
    for name in set(sys.modules) - before:
        if name.split(".")[0] in ("utils", "robot") or name.startswith(("brains.gazebo", "behavior_metrics_brain_")):
            del sys.modules[name]


def test_bm_s_default_brain_s_imports_load_with_albumentations_1_names_for_bm_files_only(
    bm_checkout, bm_imports_undone
):
    """BM's default brain imports RandomBrightness, which albumentations 2 removed: a BM file gets 1.0.3's names,
    built from 2.x's transforms; the albumentations everyone else imports is left as it is."""
    import albumentations
    import numpy as np

    from brains.base import Observation
    from brains.behavior_metrics.adapter import BehaviorMetricsBrain

    file = bm_checkout / "behavior_metrics/brains/gazebo/f1/brain_f1_opencv_imports.py"
    brain = BehaviorMetricsBrain(file=str(file), bm_root=str(bm_checkout))
    frame = np.full((480, 640, 3), 90, np.uint8)
    action = brain.act(Observation(image_rgb=frame, stamp_ns=0, seq=0))
    assert action.speed_mps == 3.0 and np.array_equal(brain.debug_images["frame_0"], frame)
    brightness = brain._brain.same.transforms[0]
    assert type(brightness).__name__ == "RandomBrightnessContrast" and brightness.contrast_limit == (0.0, 0.0)
    assert not hasattr(albumentations, "RandomBrightness")  # only the BM file's import sees 1.x's names


@pytest.mark.slow
@pytest.mark.integration
def test_a_brain_with_bm_s_default_brain_s_imports_drives_through_the_cli(bm_checkout, tmp_path):

    file = bm_checkout / "behavior_metrics/brains/gazebo/f1/brain_f1_opencv_imports.py"
    score = two_seconds_at_160x120(tmp_path, "--brain", str(file), "--brain-option", f"bm_root={bm_checkout}")
    assert score["metrics"]["completed_distance_m"] == pytest.approx(6.0, abs=0.2)  # 3 m/s, 2 s


@pytest.mark.parametrize(("transform", "hint"), [("rainy", "; did you mean 'rain'?"), ("Rain", "'rain'"), ("xyz", "")])
def test_bm_import_refuses_an_image_transform_bm_does_not_have_with_bm_s_list(bm_checkout, tmp_path, transform, hint):
    config = tmp_path / "bad.yml"
    config.write_text(CONFIG.read_text().replace("ImageTranform: 'night'", f"ImageTranform: '{transform}'"))
    out = tmp_path / "m.yaml"
    run = drivebench("bm", "import", str(config), "-o", str(out), "--bm-root", str(bm_checkout))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert f"Parameters.ImageTranform {transform!r} is not one of Behavior Metrics' options" in run.stderr
    assert "'night', 'shadow', 'snow', 'fog', 'sunflare', 'daytime', 'affine'" in run.stderr and hint in run.stderr
    assert not out.exists()


def test_bm_import_keeps_an_absolute_brain_path_absolute(bm_checkout, tmp_path):
    absolute = bm_checkout / "behavior_metrics/brains/gazebo/f1/brain_f1_keywords.py"
    config = tmp_path / "abs.yml"
    data = yaml.safe_load(CONFIG.read_text())
    data["Behaviors"]["Robot"]["BrainPath"] = [str(absolute)]
    data["Behaviors"]["Robot"]["Parameters"]["Model"] = ""
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "elsewhere" / "m.yaml"
    run = drivebench("bm", "import", str(config), "-o", str(out), "--bm-root", str(bm_checkout))
    assert run.returncode == 0, run.stderr
    assert [brain["name"] for brain in yaml.safe_load(out.read_text())["brains"]] == [str(absolute)]
    moved = tmp_path / "moved.yaml"
    out.rename(moved)  # an absolute path still names the file wherever the matrix goes
    assert [brain.label for brain in load_matrix(moved).brains] == ["brain_f1_keywords"]


# A BM-style brain (written for these tests) that crops fixed rows of BM's 640x480 frame inside its own `try`, as BM's
# brains do: at a smaller camera its crop is empty, it swallows the error and never sends a speed.
CROPPING_BRAIN = """
class Brain:
    def __init__(self, sensors, actuators, handler=None, config=None):
        self.camera = sensors.get_camera("camera_0")
        self.motors = actuators.get_motor("motors_0")

    def execute(self):
        try:
            crop = self.camera.getImage().data[240:480, 0:640]
            if crop.shape[0] == 0:
                raise ValueError("empty crop")
            self.motors.sendV(3.0)
        except Exception as err:
            print(err)
"""


@pytest.mark.slow
@pytest.mark.integration
def test_a_bm_brain_file_runs_on_bm_s_640x480_camera_unless_told_and_says_so(tmp_path):
    import json

    brain = tmp_path / "brain_f1_crops.py"
    brain.write_text(CROPPING_BRAIN)
    common = ("run", "--brain", str(brain), "--max-sim-seconds", "1", "--json")
    run = drivebench(*common, "--out", str(tmp_path / "bm"), timeout_s=170)
    assert run.returncode == 0, run.stderr
    score = json.loads(run.stdout)
    assert (score["spec"]["camera"]["width_px"], score["spec"]["camera"]["height_px"]) == (640, 480)
    assert score["metrics"]["completed_distance_m"] == pytest.approx(3.0, abs=0.2)  # its crop saw rows: it drove
    assert run.stderr.count("camera 640x480, Behavior Metrics' F1 camera, for a Behavior Metrics brain file") == 1
    run = drivebench(*common, "--camera", "160x120", "--out", str(tmp_path / "small"), timeout_s=170)
    assert run.returncode == 0, run.stderr
    assert run.stderr.count("Behavior Metrics drives it at 640x480") == 1  # the user chose: said once why it differs


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)
def test_smoke_keeps_a_bm_brain_s_camera_and_names_a_brain_that_never_moved(tmp_path):
    """At smoke's 160x120 the cropping brain's crop was empty, it swallowed the error, and smoke said "done"."""
    (tmp_path / "brain_f1_crops.py").write_text(CROPPING_BRAIN)
    (tmp_path / "brain_f1_still.py").write_text(CROPPING_BRAIN.replace("sendV(3.0)", "sendV(0.0)"))
    matrix = tmp_path / "bm.yaml"
    matrix.write_text(
        "name: bm\nbrains: [brain_f1_crops.py, brain_f1_still.py]\ncircuits: [simple]\ncamera: 640x480\n"
        "limits: {max_sim_seconds: 60}\n"
    )
    run = drivebench("matrix", str(matrix), "--smoke", "-o", str(tmp_path / "runs"), "--workers", "1", timeout_s=500)
    assert run.returncode == 0, run.stderr
    with ResultStore(tmp_path / "runs", create=False) as store:
        results = {result.brain: result for result in store.results()}
    crops = results["brain_f1_crops"]
    assert crops.score.spec.camera.width_px == 640 and crops.score.metrics.completed_distance_m > 10.0
    assert "smoke: brain_f1_still never moved" in run.stderr and "smoke: brain_f1_crops" not in run.stderr


@pytest.mark.slow
@pytest.mark.integration
def test_the_matrix_bm_import_writes_from_a_config_in_the_checkout_starts_without_bm_root(bm_checkout, tmp_path):
    """BM keeps default.yml beside brains/ and utils/: a config there names its own checkout, so the matrix written
    from it gives its brains their bm_root, and a brain importing utils.constants (as BM's default brain does)
    starts (it used to stop before the first episode: "give --brain-option bm_root=PATH")."""
    config = bm_checkout / "behavior_metrics" / "default.yml"
    data = yaml.safe_load(CONFIG.read_text())
    data["Behaviors"]["Robot"]["BrainPath"] = "brains/gazebo/f1/brain_f1_opencv_imports.py"
    data["Behaviors"]["Robot"]["Parameters"] = {"ImageTranform": ""}
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "m.yaml"
    converted = drivebench("bm", "import", str(config), "-o", str(out))
    assert converted.returncode == 0, converted.stderr
    [brain] = yaml.safe_load(out.read_text())["brains"]
    assert brain["options"]["bm_root"] == str((bm_checkout / "behavior_metrics").resolve())
    run = drivebench("matrix", str(out), "--smoke", "-o", str(tmp_path / "runs"), "--workers", "1", timeout_s=600)
    assert run.returncode == 0, run.stderr
    with ResultStore(tmp_path / "runs", create=False) as store:
        assert {result.status for result in store.results()} == {"done"}


def two_seconds_at_160x120(tmp_path, *args: str) -> dict:
    """`drivebench run ARGS` for 2 s of simulated time at 160x120: its score (the run must exit 0)."""
    import json

    run = drivebench(
        "run",
        *args,
        "--max-sim-seconds",
        "2",
        "--camera",
        "160x120",
        "--json",
        "--out",
        str(tmp_path / "run"),
        timeout_s=170,
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)
