"""Neural brains: checkpoints, ONNX export and parity, torch/onnx backends, the frame history, de-normalisation,
errors, serving an ONNX file without torch, and one closed-loop run of a brain host over Zenoh."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from needs import require

torch = require("torch")
require("onnxruntime")
onnx = require("onnx")

from brains import Observation, make_brain  # noqa: E402
from brains.nets import make_model  # noqa: E402
from brains.neural.brain import NeuralBrain  # noqa: E402
from brains.neural.checkpoint import (  # noqa: E402
    FORMAT,
    CheckpointError,
    default_input,
    load_checkpoint,
    make_random_checkpoint,
    save_checkpoint,
)
from brains.neural.export import check_parity, export_onnx  # noqa: E402
from brains.registry import BrainOptionsError  # noqa: E402
from orchestrator.cli import main  # noqa: E402

NAMES = ["pilotnet", "deepest_lstm_tiny_pilotnet", "pilotnet_x3", "memdccp"]
MS = 1_000_000


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, str]:
    folder = tmp_path_factory.mktemp("ckpts")
    return {name: str(make_random_checkpoint(folder / f"{name}.pt", name, seed=i)) for i, name in enumerate(NAMES)}


def noise_frames(n: int, *, seed: int = 0, size: tuple[int, int] = (320, 240)) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8) for _ in range(n)]


def flat_frame(value: int, size: tuple[int, int] = (320, 240)) -> np.ndarray:
    return np.full((size[1], size[0], 3), value, dtype=np.uint8)


def drive(brain, images, *, step_ms: int = 50, seqs=None) -> list:
    brain.reset(seed=0)
    seqs = range(len(images)) if seqs is None else seqs
    return [
        brain.act(Observation(image_rgb=image, stamp_ns=seq * step_ms * MS, seq=seq))
        for seq, image in zip(seqs, images)
    ]


def as_array(actions) -> np.ndarray:
    return np.array([(a.speed_mps, a.yaw_rate_radps) for a in actions])


# -- export and parity --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_onnx_export_matches_torch_and_describes_itself(name, ckpts, tmp_path):
    path = export_onnx(ckpts[name], tmp_path / f"{name}.onnx")
    assert check_parity(ckpts[name], path, batch=3) < 1e-4
    proto = onnx.load(str(path), load_external_data=False)
    meta = {prop.key: prop.value for prop in proto.metadata_props}
    assert meta["drivebench.model"] == name
    assert json.loads(meta["drivebench.input"])["offsets_s"] == list(load_checkpoint(ckpts[name]).input.offsets_s)
    assert [i.name for i in proto.graph.input] == ["frames"] and [o.name for o in proto.graph.output] == ["command"]
    assert proto.graph.input[0].type.tensor_type.shape.dim[0].dim_param == "batch"  # dynamic batch axis


def test_parity_detects_a_different_network(ckpts, tmp_path):
    other = make_random_checkpoint(tmp_path / "other.pt", "deepest_lstm_tiny_pilotnet", seed=99)
    assert check_parity(ckpts["deepest_lstm_tiny_pilotnet"], export_onnx(other, tmp_path / "o.onnx")) > 1e-3


def test_export_command_writes_the_file_and_prints_its_parity(ckpts, tmp_path, capsys):
    out = tmp_path / "sub" / "m.onnx"
    assert main(["export", ckpts["memdccp"], "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert out.is_file() and str(out) in printed
    assert float(re.search(r"max \|onnxruntime - torch\| = (\S+)", printed).group(1)) < 1e-4
    assert main(["export", str(tmp_path / "no.pt"), "-o", str(out)]) == 2
    assert capsys.readouterr().err == f"drivebench: error: {tmp_path / 'no.pt'}: no such checkpoint file\n"


# -- backends -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_torch_and_onnx_backends_give_the_same_actions(name, ckpts):
    images = noise_frames(12)
    eager = as_array(drive(NeuralBrain(weights=ckpts[name], backend="torch"), images))
    ort = as_array(drive(NeuralBrain(weights=ckpts[name], backend="onnx"), images))
    assert np.max(np.abs(eager - ort)) < 1e-4
    assert np.ptp(eager, axis=0).min() > 1e-3  # the actions do depend on the frames: the comparison means something


def test_onnx_path_is_written_then_reused_and_checked(ckpts, tmp_path):
    cache = tmp_path / "cache.onnx"
    first = as_array(drive(NeuralBrain(weights=ckpts["memdccp"], onnx_path=str(cache)), noise_frames(4)))
    assert cache.is_file()
    stamp = cache.stat().st_mtime_ns
    again = as_array(drive(NeuralBrain(weights=ckpts["memdccp"], onnx_path=str(cache)), noise_frames(4)))
    assert cache.stat().st_mtime_ns == stamp and np.array_equal(first, again)
    with pytest.raises(CheckpointError, match="exported from another checkpoint"):
        NeuralBrain(weights=ckpts["pilotnet_x3"], onnx_path=str(cache))


# -- history ------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def seq_brain(ckpts) -> NeuralBrain:
    """memDCCP, trained with frames t-9, t-5, t at 0.05 s (offsets -0.45, -0.25, 0 s)."""
    return NeuralBrain(weights=ckpts["memdccp"], backend="torch")


@pytest.mark.parametrize(
    "step_ms, offsets",
    [
        (50, (-9, -5, 0)),  # the training step: the training offsets
        (40, (-11, -6, 0)),  # 25 Hz: -0.45 s is closest to -0.44 s, -0.25 s to -0.24 s
        (100, (-5, -3, 0)),  # 10 Hz: -0.45 s lies halfway between -0.4 and -0.5 s; ties go to the older frame
    ],
)
def test_history_picks_the_frames_closest_to_the_offsets_in_seconds(seq_brain, step_ms, offsets):
    seq_brain.reset(seed=0)
    for n in range(25):
        seq_brain.act(Observation(image_rgb=flat_frame(10 * n), stamp_ns=n * step_ms * MS, seq=n))
        expected = [max(n + o, 0) for o in offsets]  # clamped to the first frame of the episode
        assert seq_brain.input_stamps_ns() == [s * step_ms * MS for s in expected], n
        x = seq_brain.model_input()
        assert x.shape == (1, 3, 3, 50, 100) and x.dtype == np.float32
        for k, s in enumerate(expected):
            assert np.array_equal(x[0, k], seq_brain.preprocess(flat_frame(10 * s))), (n, k)


def test_history_skips_a_frame_the_brain_never_saw(seq_brain):
    seqs = [s for s in range(13) if s != 7]  # frame 7 dropped on the way
    drive(seq_brain, [flat_frame(10 * s) for s in seqs], seqs=seqs)
    assert seq_brain.input_stamps_ns() == [3 * 50 * MS, 6 * 50 * MS, 12 * 50 * MS]  # 6 and 8 tie for 7: the older


def test_history_is_bounded_and_reset_clears_it(seq_brain):
    drive(seq_brain, noise_frames(30, size=(160, 120)))
    assert len(seq_brain.history) == 10  # frames t-9 .. t: older ones can never be picked again
    seq_brain.reset(seed=0)
    assert len(seq_brain.history) == 0
    fresh = flat_frame(200)
    seq_brain.act(Observation(image_rgb=fresh, stamp_ns=0, seq=0))
    assert seq_brain.input_stamps_ns() == [0, 0, 0]
    assert all(np.array_equal(frame, seq_brain.preprocess(fresh)) for frame in seq_brain.model_input()[0])


def test_single_frame_model_input_is_the_cropped_newest_frame(ckpts):
    brain = NeuralBrain(weights=ckpts["deepest_lstm_tiny_pilotnet"], backend="torch")
    image = flat_frame(0)
    image[120:] = 255  # DeepestLSTMTinyPilotNet keeps the lower half only: all white
    drive(brain, [flat_frame(60), image])
    x = brain.model_input()
    assert x.shape == (1, 3, 50, 100)
    white = (1.0 - np.array([0.485, 0.456, 0.406], dtype=np.float32)) / np.array([0.229, 0.224, 0.225], np.float32)
    assert np.allclose(x[0], white[:, None, None], atol=1e-6)


# -- de-normalisation ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_output_is_denormalised_with_the_checkpoint_label_statistics(backend, tmp_path):
    model = make_model("deepest_lstm_tiny_pilotnet")
    last = [m for m in model.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():  # constant normalised output (0.3, -0.7)
        last.weight.zero_()
        last.bias.copy_(torch.tensor([0.3, -0.7]))
    norm = {
        "image_mean": [0.5] * 3,
        "image_std": [0.25] * 3,
        "labels": "zscore",
        "label_mean": [4.0, 0.5],
        "label_std": [2.0, 0.25],
    }
    path = save_checkpoint(
        tmp_path / "c.pt",
        model_name="deepest_lstm_tiny_pilotnet",
        module=model,
        input=default_input("deepest_lstm_tiny_pilotnet"),
        normalisation=norm,
    )
    (action,) = drive(NeuralBrain(weights=str(path), backend=backend), noise_frames(1))
    assert action.speed_mps == pytest.approx(0.3 * 2.0 + 4.0, abs=1e-5)
    assert action.yaw_rate_radps == pytest.approx(-0.7 * 0.25 + 0.5, abs=1e-5)


# -- errors -------------------------------------------------------------------------------------------------------


def _write(case: str, folder, ckpts) -> str:
    path = folder / f"{case}.pt"
    good = torch.load(ckpts["deepest_lstm_tiny_pilotnet"], weights_only=True)
    if case == "missing":
        return str(folder / "nowhere" / "x.pt")
    if case == "text":
        path.write_text("not a checkpoint\n")
    elif case == "plain_dict":
        torch.save({"weights": torch.zeros(3)}, path)
    else:
        torch.save(
            {**good, **({"format": "drivebench.checkpoint.v0"} if case == "format" else {"model": "resnet"})}, path
        )
    return str(path)


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing", "no such checkpoint file"),
        ("text", "not a torch checkpoint"),
        ("plain_dict", "not a drivebench checkpoint"),
        ("format", f"format 'drivebench.checkpoint.v0', expected '{FORMAT}'"),
        ("model", "unknown model 'resnet'"),
    ],
)
def test_bad_weights_give_one_line_naming_the_file(case, message, tmp_path, ckpts):
    path = _write(case, tmp_path, ckpts)
    with pytest.raises(CheckpointError) as error:
        make_brain("neural", weights=path)
    assert str(error.value).startswith(f"{path}: ") and message in str(error.value)
    assert "\n" not in str(error.value)


def test_named_brain_refuses_another_network_and_needs_weights(ckpts):
    with pytest.raises(CheckpointError, match="holds a deepest_lstm_tiny_pilotnet network, not memdccp"):
        make_brain("memdccp", weights=ckpts["deepest_lstm_tiny_pilotnet"])
    with pytest.raises(BrainOptionsError, match=r"^brain 'neural' needs --weights CKPT"):
        make_brain("neural")  # the named networks serve their shipped weights without --weights
    with pytest.raises(BrainOptionsError, match="backend must be one of onnx, torch"):
        make_brain("neural", weights=ckpts["memdccp"], backend="tensorrt")


def test_device_option_runs_on_the_cpu_and_names_what_is_missing(ckpts):
    import torch

    images = noise_frames(3)
    on_cpu = as_array(drive(NeuralBrain(weights=ckpts["memdccp"], backend="torch", device="cpu"), images))
    automatic = as_array(drive(NeuralBrain(weights=ckpts["memdccp"], backend="torch", device="auto"), images))
    np.testing.assert_allclose(automatic, on_cpu, rtol=1e-4, atol=1e-5)
    with pytest.raises(BrainOptionsError, match="needs backend torch"):
        make_brain("memdccp", weights=ckpts["memdccp"], device="cuda")
    with pytest.raises(BrainOptionsError, match="device must be cpu, cuda, cuda:N or auto, got 'tpu'"):
        make_brain("memdccp", weights=ckpts["memdccp"], backend="torch", device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(BrainOptionsError, match="no CUDA device here"):
            make_brain("memdccp", weights=ckpts["memdccp"], backend="torch", device="cuda")


@pytest.mark.parametrize(
    "argv, line",
    [
        ([], "brain: error: brain 'neural' needs --weights CKPT (or --set options.weights=CKPT)"),
        (["--weights", "/nowhere/m.pt"], "brain: error: /nowhere/m.pt: no such checkpoint file"),
    ],
)
def test_brain_host_reports_missing_or_bad_weights_in_one_line(argv, line):
    done = subprocess.run(
        [sys.executable, "-m", "brains", "--brain", "neural", *argv], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == line
    assert "Traceback" not in done.stderr


# -- serving an exported file without torch -----------------------------------------------------------------------


def test_exported_onnx_file_serves_alone_without_torch(ckpts, tmp_path):
    onnx_file = export_onnx(ckpts["pilotnet_x3"], tmp_path / "x3.onnx")
    code = textwrap.dedent(f"""
        import json, sys
        import numpy as np
        from brains import Observation, make_brain
        brain = make_brain("pilotnet_x3", weights={str(onnx_file)!r})
        brain.reset(seed=0)
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (240, 320, 3), dtype=np.uint8) for _ in range(6)]
        actions = [brain.act(Observation(image_rgb=im, stamp_ns=i * 50_000_000, seq=i)) for i, im in enumerate(images)]
        print(json.dumps({{"torch": "torch" in sys.modules,
                          "actions": [[a.speed_mps, a.yaw_rate_radps] for a in actions]}}))
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["torch"] is False
    expected = as_array(drive(NeuralBrain(weights=ckpts["pilotnet_x3"], backend="torch"), noise_frames(6)))
    assert np.max(np.abs(np.array(result["actions"]) - expected)) < 1e-4
    with pytest.raises(CheckpointError, match="backend 'onnx' only"):
        NeuralBrain(weights=str(onnx_file), backend="torch")
    with pytest.raises(CheckpointError, match="holds a pilotnet_x3 network, not memdccp"):
        make_brain("memdccp", weights=str(onnx_file))


# -- closed loop --------------------------------------------------------------------------------------------------


@pytest.mark.integration
def test_brain_host_drives_the_closed_loop(make_stack, tmp_path):
    from orchestrator.stack.launcher import BrainLaunch
    from protocol.episode_spec import CameraSpec, EpisodeSpec
    from protocol.messages import EndReason

    name = "deepest_lstm_tiny_pilotnet"
    # Slow and nearly straight whatever the untrained network says, so the episode lasts.
    weights = make_random_checkpoint(tmp_path / "tiny.pt", name, seed=0, label_mean=(1.0, 0.0), label_std=(0.2, 0.02))
    stack = make_stack(BrainLaunch(name, options=(f"weights={json.dumps(str(weights))}",)))
    score = stack.run_episode(
        EpisodeSpec(
            circuit="simple", max_sim_seconds=15.0, active_brain=name, camera=CameraSpec(width_px=160, height_px=120)
        )
    )
    m = score.metrics
    assert score.brain == name
    assert score.reason in (EndReason.TIME_LIMIT, EndReason.OFF_TRACK, EndReason.CRASH), score.reason
    assert m.steps >= 200  # a few hundred lock-step frames (300 if it stays on the road for the 15 s)
    assert m.command_rate_hz == pytest.approx(20.0, rel=0.05)  # lock-step: every frame answered
    assert m.inference_p50_ms > 0  # the network ran (a repeated last command reports 0)
    assert m.completed_distance_m > 1.0
    log = stack.child("brain", name).log_path.read_text()
    assert "Traceback" not in log and " ERROR " not in log
