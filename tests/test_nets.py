"""The paper's four networks: Keras-exact parameter counts, shapes, Keras layer semantics, preprocessing."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from needs import require

torch = require("torch")

from torch import nn  # noqa: E402

from brains.nets import MODELS, ModelInfo, make_model  # noqa: E402
from brains.nets.layers import (  # noqa: E402
    ConvLSTM2d,
    KerasLSTM,
    KerasSameConv2d,
    KerasSameConv3d,
    keras_hard_sigmoid,
    keras_param_count,
    keras_same_pad,
    keras_same_padding,
)
from brains.nets.memdccp.model import keras_raw_reshape  # noqa: E402
from brains.nets.preprocess import (  # noqa: E402
    IMAGENET_MEAN,
    IMAGENET_STD,
    denormalise,
    normalise_labels,
    prepare_batch,
    prepare_frame,
)

NAMES = sorted(MODELS)  # every registered network: one added is tested with no edit here


def batch(info: ModelInfo, n: int = 2) -> torch.Tensor:
    shape = (n, 3, info.input_height_px, info.input_width_px)
    if info.frames > 1:
        shape = (n, info.frames) + shape[1:]
    return torch.randn(shape, generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def models() -> dict[str, nn.Module]:
    torch.manual_seed(0)
    return {name: make_model(name) for name in NAMES}


# --- registry -------------------------------------------------------------------------------------------------


def test_registry_names_and_inputs():
    assert (MODELS["pilotnet"].input_height_px, MODELS["pilotnet"].input_width_px) == (66, 200)
    # The paper's networks as the paper builds them (a network added later is checked by the tests that follow).
    paper = {"pilotnet": (1, 0.0), "deepest_lstm_tiny_pilotnet": (1, 0.5), "pilotnet_x3": (3, 0.0), "memdccp": (3, 0.0)}
    assert {n: (MODELS[n].frames, MODELS[n].crop_top_fraction) for n in paper} == paper
    for name, info in MODELS.items():
        assert info.name == name and info.frames in (1, 3) and 0.0 <= info.crop_top_fraction < 1.0, info
    with pytest.raises(ValueError, match="unknown network"):
        make_model("resnet")


def test_importing_registry_and_preprocess_does_not_import_torch():
    code = "import sys, brains.nets, brains.nets.preprocess; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


# --- parameter counts -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_keras_parameter_count_matches_reference(models, name):
    assert keras_param_count(models[name]) == MODELS[name].reference_params


@pytest.mark.parametrize(
    "name, trainable",
    [("pilotnet", 17_016_200), ("deepest_lstm_tiny_pilotnet", 62_470), ("pilotnet_x3", 352_952), ("memdccp", 910_688)],
)
def test_trainable_count_excludes_bn_moving_statistics(models, name, trainable):
    # Keras counts BN moving mean/variance (2·3 numbers on the RGB input); PyTorch keeps them as buffers.
    assert sum(p.numel() for p in models[name].parameters()) == trainable


def test_recurrent_tiny_pilotnet_uses_its_older_frames():
    """Ours: the tiny network's layers, but its ConvLSTMs recur over the three frames, so the older frames (and the
    recurrent kernels) change the answer; in the paper's networks they never do."""
    model = make_model("recurrent_tiny_pilotnet").eval()
    tiny = make_model("deepest_lstm_tiny_pilotnet")
    assert sum(p.numel() for p in model.parameters()) == sum(p.numel() for p in tiny.parameters()) == 62_470
    x = batch(MODELS["recurrent_tiny_pilotnet"])
    older_changed = x.clone()
    older_changed[:, 0] = torch.randn_like(older_changed[:, 0])
    with torch.no_grad():
        assert not torch.allclose(model(x), model(older_changed))
        for layer in model.memory:
            layer.recurrent_conv.weight.zero_()
        assert not torch.allclose(model(x), model(older_changed))  # still: the cell state carries them too


def test_recurrent_kernels_get_gradients_only_when_time_recurs():
    model = make_model("recurrent_tiny_pilotnet").train()
    nn.functional.mse_loss(model(batch(MODELS["recurrent_tiny_pilotnet"])), torch.zeros(2, 2)).backward()
    assert all(layer.recurrent_conv.weight.grad.abs().sum() > 0 for layer in model.memory)


def test_memdccp_clean_variant_count():
    assert keras_param_count(make_model("memdccp", clean=True)) == 659_894


def test_pilotnet_x3_lstm_width_is_a_setting():
    # First LSTM 4·((5824 + u)·u + u), then 3·4·(2u·u + u), Dense 1164 takes u inputs.
    u = 8
    expected = 352_958 - (93_264 + 3 * 144 + 4 * 1164) + 4 * ((5824 + u) * u + u) + 3 * 4 * (2 * u * u + u) + u * 1164
    assert keras_param_count(make_model("pilotnet_x3", lstm_units=u)) == expected


# --- forward / backward ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_output_shape(models, name):
    out = models[name].train()(batch(MODELS[name]))
    assert out.shape == (2, 2) and out.dtype == torch.float32 and torch.isfinite(out).all()


@pytest.mark.parametrize("name", NAMES)
def test_forward_backward(models, name):
    model = models[name].train()
    model.zero_grad(set_to_none=True)
    loss = nn.functional.mse_loss(model(batch(MODELS[name])), torch.full((2, 2), 0.5))
    loss.backward()
    last = [m for m in model.modules() if isinstance(m, nn.Linear)][-1]
    first = next(m for m in model.modules() if isinstance(m, (nn.Conv2d, nn.Conv3d)))
    for layer in (first, last):
        assert layer.weight.grad is not None and torch.isfinite(layer.weight.grad).all()
        assert layer.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("name", NAMES)
def test_eval_is_deterministic(models, name):
    model = models[name].eval()
    x = batch(MODELS[name])
    with torch.no_grad():
        assert torch.equal(model(x), model(x))
        # Each sample is independent of the rest of the batch in eval (BN uses its moving statistics).
        assert torch.allclose(model(x[:1]), model(x)[:1], atol=1e-5)


def test_batchnorm_uses_keras_hyperparameters(models):
    bns = [m for m in models["pilotnet"].modules() if isinstance(m, nn.BatchNorm2d)]
    assert len(bns) == 1 and bns[0].eps == 1e-3 and bns[0].momentum == 0.01


# --- Keras layer semantics ------------------------------------------------------------------------------------


def test_keras_same_padding_sizes_and_placement():
    assert keras_same_padding(66, 5, 2) == (1, 2)  # the odd extra row goes to the bottom
    assert keras_same_padding(200, 5, 2) == (1, 2)
    assert keras_same_padding(25, 3, 1) == (1, 1)
    padded = keras_same_pad(torch.ones(1, 1, 66, 200), (5, 5), (2, 2))
    assert padded.shape == (1, 1, 69, 203)
    assert padded[0, 0, 0].sum() == 0 and padded[0, 0, -2:].sum() == 0 and padded[0, 0, 1, 1:-2].min() == 1


def test_same_conv_output_sizes_follow_keras():
    x = torch.zeros(1, 3, 66, 200)
    sizes = []
    for c_in, c_out in [(3, 24), (24, 36), (36, 48)]:
        x = KerasSameConv2d(c_in, c_out, 5, stride=2)(x)
        sizes.append(tuple(x.shape[-2:]))
    assert sizes == [(33, 100), (17, 50), (9, 25)]
    assert KerasSameConv2d(48, 64, 3)(x).shape == (1, 64, 9, 25)
    y = torch.zeros(1, 3, 3, 50, 100)
    y = KerasSameConv3d(3, 24, 5, stride=2)(y)
    assert y.shape == (1, 24, 2, 25, 50)
    y = KerasSameConv3d(24, 36, 5, stride=2)(y)
    assert y.shape == (1, 36, 1, 13, 25)


def test_same_conv_matches_manual_asymmetric_padding():
    conv = KerasSameConv2d(2, 3, 4, stride=2)
    x = torch.randn(1, 2, 9, 10)
    # TF: 9 rows -> 5, total pad (5-1)·2+4-9 = 3 -> (1 top, 2 bottom); 10 cols -> 5, total 2 -> (1, 1).
    expected = nn.functional.conv2d(nn.functional.pad(x, (1, 1, 1, 2)), conv.weight, conv.bias, stride=2)
    assert torch.allclose(conv(x), expected)


def test_hard_sigmoid_is_keras_2():
    got = keras_hard_sigmoid(torch.tensor([-3.0, -1.0, 0.0, 1.0, 3.0]))
    assert torch.allclose(got, torch.tensor([0.0, 0.3, 0.5, 0.7, 1.0]))


@pytest.mark.parametrize("c_in, filters, k", [(7, 8, 5), (8, 8, 5), (64, 8, 5), (3, 16, 3)])
def test_convlstm_param_count(c_in, filters, k):
    assert keras_param_count(ConvLSTM2d(c_in, filters, k)) == 4 * (k * k * (c_in + filters) * filters + filters)


def test_convlstm_first_step_is_a_gated_conv_and_later_steps_recur():
    torch.manual_seed(0)
    cell = ConvLSTM2d(3, 4, 3, return_sequences=True)
    x = torch.randn(2, 1, 3, 5, 6).expand(2, 2, 3, 5, 6)  # the same frame twice
    out = cell(x)
    assert out.shape == (2, 2, 4, 5, 6)
    i, f, g, o = cell.input_conv(x[:, 0]).chunk(4, dim=1)
    sig = keras_hard_sigmoid
    assert torch.allclose(out[:, 0], sig(o) * torch.tanh(sig(i) * torch.tanh(g)), atol=1e-6)
    c1 = sig(i) * torch.tanh(g)
    i2, f2, g2, o2 = (cell.input_conv(x[:, 1]) + cell.recurrent_conv(out[:, 0])).chunk(4, dim=1)
    c2 = sig(f2) * c1 + sig(i2) * torch.tanh(g2)
    assert torch.allclose(out[:, 1], sig(o2) * torch.tanh(c2), atol=1e-6)  # step 2 uses h and c of step 1
    last_only = ConvLSTM2d(3, 4, 3, return_sequences=False)
    last_only.load_state_dict(cell.state_dict())
    assert torch.allclose(last_only(x), out[:, -1])


def test_keras_lstm_matches_torch_lstm_with_one_bias():
    torch.manual_seed(0)
    ours = KerasLSTM(6, 4, return_sequences=True)
    ref = nn.LSTM(6, 4, batch_first=True)
    with torch.no_grad():
        ref.weight_ih_l0.copy_(ours.weight_ih)
        ref.weight_hh_l0.copy_(ours.weight_hh)
        ref.bias_ih_l0.copy_(ours.bias)
        ref.bias_hh_l0.zero_()
    x = torch.randn(2, 3, 6)
    assert torch.allclose(ours(x), ref(x)[0], atol=1e-6)
    assert sum(p.numel() for p in ours.parameters()) == 4 * ((6 + 4) * 4 + 4)
    assert torch.equal(ours.bias[4:8], torch.ones(4))  # forget bias 1


def test_memdccp_raw_reshape_is_keras_row_major():
    feats = torch.arange(64 * 7 * 13, dtype=torch.float32).reshape(1, 64, 1, 7, 13)  # (B, C, T, H, W)
    keras_flat = feats.permute(0, 2, 3, 4, 1).flatten()  # Keras memory order (T, H, W, C)
    seq = keras_raw_reshape(feats)
    assert seq.shape == (1, 1, 7, 13, 64)
    for k, i, j in [(0, 0, 0), (6, 12, 63), (3, 5, 17), (1, 0, 1)]:
        # Keras (13, 64, 7)[i, j, k] is flat element (i·64 + j)·7 + k; ours holds it at channel k, row i, col j.
        assert seq[0, 0, k, i, j] == keras_flat[(i * 64 + j) * 7 + k]
    assert not torch.equal(seq, feats.reshape(1, 1, 7, 13, 64))  # not a plain channels-first reshape


# --- preprocessing --------------------------------------------------------------------------------------------


def test_label_round_trip_and_clipping():
    v = np.array([6.5, 10.0, 24.0])
    w = np.array([-7.1, 0.0, 3.2])
    y = normalise_labels(v, w)
    assert y.shape == (3, 2) and y.dtype == np.float32
    assert np.allclose(y[1], [(10.0 - 6.5) / 17.5, 0.5])
    v2, w2 = denormalise(y)
    assert np.allclose(v2, v, atol=1e-5) and np.allclose(w2, w, atol=1e-5)
    assert np.allclose(normalise_labels(3.0, 9.0), [0.0, 1.0])  # out of range: clipped


def test_prepare_frame_crops_resizes_and_normalises():
    frame = np.zeros((480, 640, 3), np.uint8)
    frame[240:] = 255  # black top half, white bottom half
    white = (1.0 - IMAGENET_MEAN) / IMAGENET_STD
    x = prepare_frame(frame, MODELS["deepest_lstm_tiny_pilotnet"])
    assert x.shape == (3, 50, 100) and x.dtype == np.float32 and x.flags["C_CONTIGUOUS"]
    assert np.allclose(x, white[:, None, None], atol=1e-5)  # only the bottom half survives the crop
    y = prepare_frame(frame, MODELS["pilotnet"])
    assert y.shape == (3, 66, 200)
    assert np.allclose(y[:, 0], (-IMAGENET_MEAN / IMAGENET_STD)[:, None], atol=1e-5)  # uncropped: black on top


def test_prepare_batch_matches_prepare_frame():
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (4, 50, 100, 3), dtype=np.uint8)
    info = MODELS["memdccp"]
    got = prepare_batch(frames, info)
    assert got.shape == (4, 3, 50, 100) and got.dtype == np.float32
    assert np.allclose(got[2], prepare_frame(frames[2], info))
    with pytest.raises(ValueError):
        prepare_batch(frames, MODELS["pilotnet"])  # wrong size for 66x200
