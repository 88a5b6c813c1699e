"""The noise models and pipeline, as pure code: statistics, exact values, delays, drops, seeding, validation."""

from __future__ import annotations

import math
import os
import sys

import msgspec
import numpy as np
import pytest
from needs import require

from protocol.episode_spec import (
    NOISE_MODELS,
    Affine,
    Blur,
    Brightness,
    Daytime,
    Delay,
    Drop,
    Fog,
    Gaussian,
    Jpeg,
    Night,
    NoiseStage,
    Occlusion,
    Rain,
    SaltPepper,
    Shadow,
    Snow,
    Sunflare,
)
from protocol.variations import VariationError, noise_stage
from services.noise.models import DelayModel, MissingExtra, NoiseModel, NoisePipeline, make_model, require_extras

os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")  # albumentations asks PyPI for updates at import otherwise

H, W = 120, 160

# One stage of every type, with parameters that change (nearly) every frame; random ones first.
RANDOM_STAGES: list[NoiseStage] = [
    SaltPepper(probability=0.3),
    Gaussian(sigma=12.0),
    Occlusion(patches=2, size_fraction=0.25, probability=0.7),
    Drop(probability=0.4),
]
DETERMINISTIC_STAGES: list[NoiseStage] = [
    Blur(kernel_px=5),
    Brightness(brightness=-0.2, contrast=1.3),
    Jpeg(quality=60),
    Delay(frames=2),
]
# A model added to protocol.episode_spec.NOISE_MODELS is tested by every contract test below with no edit here,
# built with its defaults (test_make_model_covers_every_stage_type names one that has none: give it defaults or a stage
# above).
_LISTED = {type(stage) for stage in RANDOM_STAGES + DETERMINISTIC_STAGES}
ALL_STAGES = (
    RANDOM_STAGES
    + DETERMINISTIC_STAGES
    + [
        model()
        for model in NOISE_MODELS
        if model not in _LISTED and not any(f.required for f in msgspec.structs.fields(model))
    ]
)


def stage_id(stage: NoiseStage) -> str:
    return type(stage).__name__


def textured(height: int = H, width: int = W, seed: int = 0) -> np.ndarray:
    """A camera-like frame: smooth colour gradients, a few edges, mild sensor noise; read-only like a bus payload."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    image = np.stack([40 + 150 * x / width, 60 + 120 * y / height, 128 + 60 * np.sin(x / 9.0 + y / 13.0)], axis=2)
    image[height // 3 : height // 2, width // 4 : width // 2] = (220, 30, 30)  # a red block: sharp edges
    image += rng.normal(0.0, 3.0, image.shape)
    out = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    out.flags.writeable = False
    return out


def constant(value: int, height: int = H, width: int = W) -> np.ndarray:
    return np.full((height, width, 3), value, dtype=np.uint8)


def run(model: NoiseModel | NoisePipeline, frames: list[np.ndarray]) -> list[np.ndarray | None]:
    return [model.apply(frame) for frame in frames]


def same_outputs(a: list[np.ndarray | None], b: list[np.ndarray | None]) -> bool:
    assert len(a) == len(b)
    return all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
        for x, y in zip(a, b, strict=True)
    )


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


# -- salt and pepper --


@pytest.mark.parametrize("probability", [0.2, 0.4, 0.6])
def test_salt_pepper_changes_a_fraction_p_of_pixels_half_black_half_white(probability):
    model = make_model(SaltPepper(probability=probability))
    model.reset(seed=7)
    grey = constant(128, 300, 400)  # 120 000 pixels: binomial std of the fraction < 0.0015
    out = model.apply(grey)
    white = np.all(out == 255, axis=2)
    black = np.all(out == 0, axis=2)
    kept = np.all(out == 128, axis=2)
    assert np.all(white | black | kept)  # a pixel changes as a whole, to pure black or pure white
    assert (white | black).mean() == pytest.approx(probability, abs=0.01)
    assert white.mean() == pytest.approx(probability / 2, abs=0.01)
    assert black.mean() == pytest.approx(probability / 2, abs=0.01)


def test_salt_pepper_extremes():
    image = textured()
    model = make_model(SaltPepper(probability=1.0))
    out = model.apply(image)
    assert np.all(np.all(out == 0, axis=2) | np.all(out == 255, axis=2))
    assert make_model(SaltPepper(probability=0.0)).apply(image) is image


def test_salt_pepper_tiny_images_take_another_code_path_with_the_same_result():
    # The first 16 random words go to the first 16 pixels whatever the image size: a 4 x 4 image (NumPy path) and
    # the first row of a 16 x 16 one (OpenCV path) get the same noise.
    big = np.array(textured(16, 16))
    small = big[0].reshape(4, 4, 3).copy()
    outputs = []
    for image in (small, big):
        model = make_model(SaltPepper(probability=0.5))
        model.reset(seed=2)
        outputs.append(model.apply(image))
    assert np.array_equal(outputs[0].reshape(16, 3), outputs[1][0])
    assert not np.array_equal(outputs[0], small)


def test_salt_pepper_noise_differs_from_frame_to_frame():
    model = make_model(SaltPepper(probability=0.3))
    first, second = model.apply(constant(128)), model.apply(constant(128))
    assert not np.array_equal(first, second)


# -- gaussian --


@pytest.mark.parametrize("sigma", [3.0, 10.0, 25.0])
def test_gaussian_residual_has_std_sigma_and_zero_mean_on_mid_grey(sigma):
    model = make_model(Gaussian(sigma=sigma))
    model.reset(seed=3)
    grey = constant(128, 200, 200)
    residual = model.apply(grey).astype(np.float64) - 128
    expected_std = math.sqrt(sigma**2 + 1 / 12)  # rounding to integers adds 1/12 of variance
    assert residual.std() == pytest.approx(expected_std, rel=0.02)
    assert abs(residual.mean()) < 0.05 * sigma
    # independent per channel, and gaussian-shaped: round(sigma * z) is within n sigma when |z| < n + 0.5 / sigma
    channels = residual.reshape(-1, 3).T
    assert abs(np.corrcoef(channels)[0, 1]) < 0.02
    for n in (1, 2):
        expected = math.erf((n + 0.5 / sigma) / math.sqrt(2))  # 0.68 and 0.95 when sigma is large
        assert np.mean(np.abs(residual) <= n * sigma) == pytest.approx(expected, abs=0.01)


def test_gaussian_clips_instead_of_wrapping():
    model = make_model(Gaussian(sigma=20.0))
    white = model.apply(constant(250))
    black = model.apply(constant(5))
    assert white.max() == 255 and white.min() > 150  # a wrap-around would give values near 0
    assert black.min() == 0 and black.max() < 100
    assert np.mean(white == 255) > 0.3  # clipped mass piles up at the bound


def test_gaussian_with_zero_sigma_is_the_identity():
    image = textured()
    assert make_model(Gaussian(sigma=0.0)).apply(image) is image


# -- brightness / contrast --


def test_brightness_and_contrast_exact_values():
    levels = np.array([0, 64, 100, 101, 128, 200, 255], dtype=np.uint8)
    image = np.broadcast_to(levels[None, :, None], (2, len(levels), 3))
    # out = 1.5 * (in - 128) + 128 + 51: -13 -> 0, 83, 137, 138.5 -> 138 (ties to even), 179, 287 -> 255, 369.5 -> 255
    brighter = make_model(Brightness(brightness=0.2, contrast=1.5)).apply(image)
    assert brighter[0, :, 0].tolist() == [0, 83, 137, 138, 179, 255, 255]
    # out = 1.2 * (in - 128) + 128 - 76.5: -102.1 -> 0, -25.3 -> 0, 17.9 -> 18, 19.1 -> 19, 51.5 -> 52 (ties to even),
    # 137.9 -> 138, 203.9 -> 204
    darker = make_model(Brightness(brightness=-0.3, contrast=1.2)).apply(image)
    assert darker[0, :, 0].tolist() == [0, 0, 18, 19, 52, 138, 204]
    assert np.array_equal(darker[:, :, 0], darker[:, :, 2]) and np.array_equal(darker[0], darker[1])
    flat = make_model(Brightness(brightness=0.1, contrast=0.0)).apply(image)  # 128 + 25.5 -> 154 (ties to even)
    assert np.all(flat == 154)
    assert make_model(Brightness()).apply(image) is image


# -- blur --


def test_blur_reduces_variance_more_with_a_larger_kernel_and_keeps_flat_areas():
    rng = np.random.default_rng(0)
    noisy = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    variances = [make_model(Blur(kernel_px=k)).apply(noisy).astype(np.float64).var() for k in (1, 3, 5, 9)]
    assert variances[0] == pytest.approx(noisy.astype(np.float64).var())
    assert variances[1] < 0.5 * variances[0]
    assert variances[0] > variances[1] > variances[2] > variances[3]
    blurred = make_model(Blur(kernel_px=5)).apply(noisy)
    assert abs(blurred.astype(np.float64).mean() - noisy.astype(np.float64).mean()) < 1.0
    assert np.array_equal(make_model(Blur(kernel_px=7)).apply(constant(77)), constant(77))


# -- occlusion --


def test_one_occlusion_patch_is_one_black_rectangle_of_size_fraction_of_each_side():
    model = make_model(Occlusion(patches=1, size_fraction=0.2))
    for _ in range(20):
        out = model.apply(constant(200))
        black = np.all(out == 0, axis=2)
        assert np.all(black | np.all(out == 200, axis=2))
        rows, cols = np.nonzero(black)
        assert (rows.max() - rows.min() + 1, cols.max() - cols.min() + 1) == (round(0.2 * H), round(0.2 * W))
        assert black.sum() == round(0.2 * H) * round(0.2 * W)  # a filled rectangle
        assert black.mean() == pytest.approx(0.2**2)


def test_occlusion_covers_about_patches_times_size_fraction_squared():
    model = make_model(Occlusion(patches=2, size_fraction=0.2))
    model.reset(seed=11)
    covered = [np.all(model.apply(constant(200)) == 0, axis=2).mean() for _ in range(300)]
    assert max(covered) <= 2 * 0.2**2 + 1e-12
    assert min(covered) >= 0.2**2 - 1e-12
    # random placement overlaps a little: expected 0.08 - 0.0021
    assert np.mean(covered) == pytest.approx(2 * 0.2**2, abs=0.005)
    assert np.mean(covered) < 2 * 0.2**2


def test_occlusion_fires_in_a_fraction_probability_of_frames():
    image = constant(200, 40, 50)
    model = make_model(Occlusion(patches=3, size_fraction=0.1, probability=0.3))
    outputs = [model.apply(image) for _ in range(1000)]
    fired = [out is not image for out in outputs]
    assert np.mean(fired) == pytest.approx(0.3, abs=0.05)
    assert all(np.any(out == 0) for out, hit in zip(outputs, fired, strict=True) if hit)


# -- jpeg --


def test_jpeg_is_close_but_lossy_and_worse_at_lower_quality():
    image = textured()
    psnrs = {}
    for quality in (10, 40, 75, 95):
        out = make_model(Jpeg(quality=quality)).apply(image)
        assert out.shape == image.shape and not np.array_equal(out, image)
        psnrs[quality] = psnr(out, image)
    assert 20 < psnrs[10] < psnrs[40] < psnrs[75] < psnrs[95] < 60
    assert psnrs[75] > 28


def test_jpeg_keeps_colours_in_rgb_order():
    image = np.zeros((64, 64, 3), np.uint8)
    image[..., 0] = 220  # pure-ish red: a BGR/RGB mix-up would turn it blue
    out = make_model(Jpeg(quality=50)).apply(image)
    assert out[..., 0].mean() > 200 and out[..., 2].mean() < 20


# -- delay --


def numbered_frames(count: int) -> list[np.ndarray]:
    return [constant(value, 8, 10) for value in range(count)]


def values(outputs: list[np.ndarray | None]) -> list[int | None]:
    result = []
    for out in outputs:
        if out is None:
            result.append(None)
        else:
            assert np.all(out == out.flat[0])
            result.append(int(out.flat[0]))
    return result


@pytest.mark.parametrize("frames", [1, 3, 7])
def test_delay_shows_the_frame_k_earlier_and_the_first_one_meanwhile(frames):
    model = make_model(Delay(frames=frames))
    outputs = values(run(model, numbered_frames(30)))
    assert outputs == [max(0, t - frames) for t in range(30)]


def test_delay_zero_is_the_identity():
    image = textured()
    assert make_model(Delay(frames=0)).apply(image) is image


def test_delay_copies_what_it_buffers():
    model = make_model(Delay(frames=2))
    reused = np.zeros((8, 10, 3), np.uint8)  # the caller fills the same array every frame
    seen = []
    for value in range(6):
        reused[...] = value
        seen.append(model.apply(reused))
    assert values(seen) == [0, 0, 0, 1, 2, 3]
    assert not any(out is reused for out in seen)
    with pytest.raises(ValueError):  # handed out read-only: nobody can change the buffered frame
        seen[-1][0, 0, 0] = 9


def test_reset_empties_the_delay_buffer():
    model = make_model(Delay(frames=2))
    run(model, numbered_frames(5))
    model.reset(seed=0)
    assert values(run(model, [constant(v, 8, 10) for v in (50, 51, 52, 53)])) == [50, 50, 50, 51]


# -- drop --


def test_drop_loses_a_fraction_probability_of_frames_and_passes_the_rest_untouched():
    image = textured(20, 30)
    model = make_model(Drop(probability=0.3))
    model.reset(seed=5)
    outputs = [model.apply(image) for _ in range(3000)]
    dropped = [out is None for out in outputs]
    assert np.mean(dropped) == pytest.approx(0.3, abs=0.03)  # binomial std 0.008
    assert all(out is image for out in outputs if out is not None)
    assert all(make_model(Drop(probability=1.0)).apply(image) is None for _ in range(50))
    never = make_model(Drop(probability=0.0))
    assert all(never.apply(image) is image for _ in range(50))


# -- every model: shape, input untouched, seeding --


def frame_sequence(count: int = 6) -> list[np.ndarray]:
    return [textured(seed=seed) for seed in range(count)]


@pytest.mark.parametrize("stage", ALL_STAGES, ids=stage_id)
@pytest.mark.parametrize("size", [(H, W), (67, 201), (1, 1), (2, 3)])
def test_every_model_keeps_shape_and_dtype(stage, size):
    model = make_model(stage)
    for frame in [constant(90, *size), textured(*size)]:
        out = model.apply(frame)
        if out is not None:
            assert out.shape == frame.shape and out.dtype == np.uint8


@pytest.mark.parametrize("stage", ALL_STAGES, ids=stage_id)
def test_every_model_leaves_its_input_untouched(stage):
    model = make_model(stage)
    writable = [np.array(frame) for frame in frame_sequence()]  # writable: a model writing would succeed silently
    before = [frame.copy() for frame in writable]
    outputs = run(model, writable) + run(model, frame_sequence())  # read-only ones would raise if written to
    assert all(np.array_equal(a, b) for a, b in zip(writable, before, strict=True))
    if not isinstance(stage, Drop | Delay | Occlusion):  # those may hand their input on as it is
        assert all(out is not None and out is not frame for out, frame in zip(outputs, writable, strict=False))


def test_a_non_contiguous_view_is_accepted():
    image = np.ascontiguousarray(textured(H, 2 * W))[:, ::2]
    assert not image.flags.c_contiguous
    for stage in ALL_STAGES:
        out = make_model(stage).apply(image)
        assert out is None or out.shape == image.shape


@pytest.mark.parametrize("stage", ALL_STAGES, ids=stage_id)
def test_same_seed_same_outputs_and_reset_restarts_the_sequence(stage):
    frames = frame_sequence()
    first, second = make_model(stage), make_model(stage)
    first.reset(seed=42)
    second.reset(seed=42)
    reference = run(first, frames)
    assert same_outputs(reference, run(second, frames))
    first.reset(seed=42)
    assert same_outputs(reference, run(first, frames))


@pytest.mark.parametrize("stage", RANDOM_STAGES, ids=stage_id)
def test_different_seeds_give_different_outputs(stage):
    frames = frame_sequence(12)
    outputs = []
    for seed in (1, 2, -1):
        model = make_model(stage)
        model.reset(seed=seed)
        outputs.append(run(model, frames))
    assert not same_outputs(outputs[0], outputs[1])
    assert not same_outputs(outputs[0], outputs[2])
    assert not same_outputs(outputs[1], outputs[2])


@pytest.mark.parametrize("stage", RANDOM_STAGES, ids=stage_id)
def test_a_random_model_does_not_repeat_itself_over_frames(stage):
    model = make_model(stage)
    model.reset(seed=0)
    outputs = run(model, [constant(128)] * 12)
    assert not same_outputs(outputs[:6], outputs[6:])


def test_make_model_covers_every_stage_type_and_rejects_others():
    for stage in ALL_STAGES:
        assert type(stage) in NOISE_MODELS
        assert make_model(stage).stage is stage
    untested = set(NOISE_MODELS) - {type(stage) for stage in ALL_STAGES}
    assert not untested, f"noise models with required parameters and no stage in this file: {untested}"
    with pytest.raises(TypeError, match="not a noise stage"):
        make_model({"model": "blur", "kernel_px": 3})


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((10, 10), np.uint8),
        np.zeros((10, 10, 4), np.uint8),
        np.zeros((10, 10, 3), np.float32),
        np.zeros((0, 10, 3), np.uint8),
        [[1, 2, 3]],
    ],
)
@pytest.mark.parametrize("stage", ALL_STAGES, ids=stage_id)
def test_a_bad_image_is_a_clear_value_error(stage, bad):
    with pytest.raises(ValueError, match="H x W x 3 uint8|NumPy array"):
        make_model(stage).apply(bad)


# -- pipeline --


def test_an_empty_pipeline_returns_its_input_object():
    pipeline = NoisePipeline([])
    pipeline.reset(seed=3)
    image = textured()
    assert pipeline.apply(image) is image
    assert len(pipeline) == 0


def test_a_pipeline_applies_its_stages_in_order():
    image = textured()
    pipeline = NoisePipeline([Brightness(brightness=0.1), Blur(kernel_px=5)])
    by_hand = make_model(Blur(kernel_px=5)).apply(make_model(Brightness(brightness=0.1)).apply(image))
    other_order = make_model(Brightness(brightness=0.1)).apply(make_model(Blur(kernel_px=5)).apply(image))
    out = pipeline.apply(image)
    assert np.array_equal(out, by_hand)
    assert not np.array_equal(out, other_order)  # brightness clips, so the order matters


def test_a_pipeline_is_reproducible_and_its_seed_matters():
    stages = [
        SaltPepper(probability=0.2),
        Gaussian(sigma=8.0),
        Occlusion(patches=2, size_fraction=0.2, probability=0.5),
        Jpeg(quality=70),
        Delay(frames=2),
        Drop(probability=0.3),
    ]
    frames = frame_sequence(10)

    def outputs(seed: int) -> list[np.ndarray | None]:
        pipeline = NoisePipeline(stages)
        pipeline.reset(seed=seed)
        return run(pipeline, frames)

    reference = outputs(9)
    assert same_outputs(reference, outputs(9))
    assert not same_outputs(reference, outputs(10))
    pipeline = NoisePipeline(stages)
    pipeline.reset(seed=9)
    run(pipeline, frame_sequence(4))
    pipeline.reset(seed=9)
    assert same_outputs(reference, run(pipeline, frames))


def test_stages_have_independent_generators():
    frames = [constant(128)] * 20
    alone = NoisePipeline([Drop(probability=0.5)])
    appended = NoisePipeline([Drop(probability=0.5), SaltPepper(probability=0.3), Gaussian(sigma=5.0)])
    alone.reset(seed=4)
    appended.reset(seed=4)
    dropped_alone = [out is None for out in run(alone, frames)]
    assert [out is None for out in run(appended, frames)] == dropped_alone  # appending stages keeps the drops
    assert 0 < sum(dropped_alone) < len(frames)
    # two stages of the same kind in one pipeline do not draw the same noise
    twice = NoisePipeline([SaltPepper(probability=0.2), SaltPepper(probability=0.2)])
    once = NoisePipeline([SaltPepper(probability=0.2)])
    once.reset(seed=4)
    changed_once = np.any(once.apply(constant(128)) != 128, axis=2).mean()
    changed_twice = np.any(twice.apply(constant(128)) != 128, axis=2).mean()
    assert changed_twice == pytest.approx(1 - 0.8**2, abs=0.02)  # not 0.2, as identical masks would give
    assert changed_once == pytest.approx(0.2, abs=0.02)


def test_a_drop_skips_the_stages_after_it():
    pipeline = NoisePipeline([Drop(probability=1.0), SaltPepper(probability=0.5)])
    assert all(pipeline.apply(textured()) is None for _ in range(5))


@pytest.mark.parametrize("frames", [1, 3])
def test_a_delay_after_a_drop_still_counts_camera_frames(frames):
    # The drops the pipeline's first stage makes, seen alone (same seed, same stage index: the same draws).
    count, seed = 60, 8
    dropping = NoisePipeline([Drop(probability=0.4)])
    dropping.reset(seed=seed)
    lost = [out is None for out in run(dropping, numbered_frames(count))]
    assert 0 < sum(lost) < count
    pipeline = NoisePipeline([Drop(probability=0.4), Delay(frames=frames), Brightness(brightness=0.0, contrast=1.0)])
    pipeline.reset(seed=seed)
    outputs = values(run(pipeline, numbered_frames(count)))
    # at time t the brain gets frame t - k, or nothing when that frame was lost; the first frame meanwhile
    assert outputs == [None if lost[max(0, t - frames)] else max(0, t - frames) for t in range(count)]


def test_stages_after_a_delay_perturb_the_delayed_frame():
    pipeline = NoisePipeline([Delay(frames=1), Brightness(brightness=0.1)])
    outputs = values(run(pipeline, [constant(v, 8, 10) for v in (10, 20, 30)]))
    assert outputs == [36, 36, 46]  # frame 10, 10, 20 each brightened by round(25.5) = 26 (ties to even)


def test_a_pipeline_rejects_something_that_is_not_a_stage():
    with pytest.raises(TypeError, match="not a noise stage"):
        NoisePipeline([Blur(kernel_px=3), "jpeg"])


def test_a_pipeline_is_built_from_a_decoded_spec_list():
    decoded = msgspec.json.decode(
        b'[{"model": "salt_pepper", "probability": 0.2}, {"model": "delay", "frames": 2}]', type=list[NoiseStage]
    )
    pipeline = NoisePipeline(decoded)
    assert isinstance(pipeline.models[1], DelayModel)
    assert pipeline.apply(constant(128)) is not None


# -- validation of the stage structs --


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Jpeg(quality=500), "jpeg quality must be within 1..100, got 500"),
        (lambda: Jpeg(quality=0), "jpeg quality"),
        (lambda: SaltPepper(probability=1.5), "salt_pepper probability must be within 0..1"),
        (lambda: SaltPepper(probability=float("nan")), "salt_pepper probability"),
        (lambda: Gaussian(sigma=-1.0), "gaussian sigma must be >= 0"),
        (lambda: Gaussian(sigma=float("nan")), "gaussian sigma"),
        (lambda: Blur(kernel_px=4), "blur kernel_px must be an odd number"),
        (lambda: Blur(kernel_px=0), "blur kernel_px"),
        (lambda: Brightness(brightness=1.5), "brightness must be within -1..1"),
        (lambda: Brightness(contrast=-0.5), "contrast >= 0"),
        (lambda: Occlusion(size_fraction=0.0), "size_fraction within"),
        (lambda: Occlusion(patches=-1), "patches >= 0"),
        (lambda: Occlusion(probability=2.0), "occlusion probability"),
        (lambda: Delay(frames=-1), "delay frames must be within 0.."),
        (lambda: Drop(probability=-0.1), "drop probability"),
    ],
)
def test_invalid_stage_parameters_raise_a_clear_value_error(build, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.").replace("(", r"\(")):
        build()


@pytest.mark.parametrize("contrast", [float("nan"), float("inf")])
def test_a_non_finite_contrast_is_refused(contrast):
    with pytest.raises(ValueError, match="contrast"):  # by the struct or, as long as it lets them through, the model
        make_model(Brightness(contrast=contrast))


def test_invalid_stage_parameters_from_the_wire_name_the_field():
    with pytest.raises(msgspec.ValidationError, match="quality"):
        msgspec.json.decode(b'{"model": "jpeg", "quality": 500}', type=NoiseStage)
    with pytest.raises(msgspec.ValidationError, match="noise"):
        msgspec.json.decode(b'{"noise": [{"model": "blur", "kernel_px": 4}]}', type=_NoiseHolder)
    with pytest.raises(msgspec.ValidationError, match="sigmaa"):
        msgspec.json.decode(b'{"model": "gaussian", "sigmaa": 3}', type=NoiseStage)
    with pytest.raises(msgspec.ValidationError, match="hail"):
        msgspec.json.decode(b'{"model": "hail"}', type=NoiseStage)
    assert msgspec.json.decode(b'{"model": "fog"}', type=NoiseStage) == Fog()  # BM's fog takes no parameters


class _NoiseHolder(msgspec.Struct):
    noise: list[NoiseStage]


def test_seeds_can_be_negative_and_must_be_ints():
    a, b = make_model(SaltPepper(probability=0.3)), make_model(SaltPepper(probability=0.3))
    a.reset(seed=-1)
    b.reset(seed=1)
    assert not np.array_equal(a.apply(constant(128)), b.apply(constant(128)))
    with pytest.raises(TypeError):
        a.reset(seed=1.5)


# -- Behavior Metrics' perturbations (albumentations, as BM's transform_image) --

BM_RANDOM = [Rain(), Shadow(), Snow(), Fog(), Sunflare()]


def test_bm_night_daytime_and_affine_are_bm_s_exact_transforms():
    require("albumentations")
    night = make_model(Night()).apply(constant(200))
    assert np.all(np.abs(night.astype(int) - 72) <= 1)  # brightness -0.5 of the full range: 200 - 127.5
    daytime = make_model(Daytime()).apply(constant(100))
    assert np.all(np.abs(daytime.astype(int) - 176) <= 1)  # +0.3: 100 + 76.5
    image = textured()
    shifted = make_model(Affine()).apply(image)
    # 10 % of the width to the left: column c shows column c + 16; the right-hand strip is black
    assert np.abs(shifted[:, 10:100].astype(int) - image[:, 26:116].astype(int)).mean() < 2
    assert np.all(shifted[:, -8:] == 0)


@pytest.mark.parametrize("stage", BM_RANDOM, ids=stage_id)
def test_bm_random_perturbations_depend_on_the_seed_and_change_from_frame_to_frame(stage):
    require("albumentations")
    frames = [textured()] * 4
    outputs = []
    for seed in (1, 2):
        model = make_model(stage)
        model.reset(seed=seed)
        outputs.append(run(model, frames))
    assert not same_outputs(outputs[0], outputs[1])
    assert not same_outputs(outputs[0][:2], outputs[0][2:])


def test_bm_perturbations_are_named_as_bm_names_them_and_take_no_value():
    assert [noise_stage(name) for name in ("rain", "night", "affine")] == [Rain(), Night(), Affine()]
    assert noise_stage({"fog": None}) == Fog()
    with pytest.raises(VariationError, match="noise model rain takes no value"):
        noise_stage("rain=0.5")


def test_without_albumentations_bm_perturbations_are_refused_in_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "albumentations", None)  # as where it is not installed
    require_extras([SaltPepper(probability=0.1)])  # drivebench's own models need nothing more
    with pytest.raises(MissingExtra, match=r"noise model night needs albumentations: pip install 'drivebench\[bm\]'"):
        require_extras([Blur(kernel_px=3), Night()])
