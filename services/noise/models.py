"""Camera perturbations as plain, seeded NumPy/OpenCV models: the pure core of the noise injector (no bus).

One model class per noise stage of ``protocol.episode_spec`` (``SaltPepper``, ``Gaussian``, ``Blur``, ``Brightness``,
``Occlusion``, ``Jpeg``, ``Delay``, ``Drop``), and one for Behavior Metrics' perturbations (``Rain``, ``Night``,
``Daytime``, ``Shadow``, ``Snow``, ``Fog``, ``Sunflare``, ``Affine``, as BM applies them: rain, shadow, snow, fog and
sunflare drawn by ``services.noise.bm`` as albumentations 1.0.3 (BM's pin) draws them; night, daytime and affine by
albumentations itself, from the optional extra ``drivebench[bm]``, whose 2.x gives 1.0.3's exact output for them);
the struct's docstring defines what the stage does, the model class says how.
Every model has

  * ``reset(*, seed)``: start a new episode: (re)seed its generator, clear its state (Delay's buffer);
  * ``apply(image_rgb) -> image_rgb | None``: perturb one camera frame, ``H x W x 3`` uint8 RGB in, the same shape and
    dtype out; ``None`` means this frame is dropped (the brain gets no new image).

``make_model(stage)`` builds the model of one stage; ``NoisePipeline(stages)`` composes them in order.

Contract shared by every model:

  * The input is never written to (it may be a read-only view on a bus payload).
  * The output is either a new array or, when a stage leaves a frame as it is (Drop keeping it, Occlusion not firing,
    Delay(0), Blur(1), Brightness(0, 1), zero noise), the input object itself. Delay returns read-only copies, some of
    them more than once. Treat every output as read-only; copy before modifying it.
  * Seeded: the same seed and the same input sequence give bitwise-identical outputs (on one machine and library
    build: JPEG goes through the system's libjpeg). A model is usable right after construction (seed 0).
  * Per-frame cost is kept to a few ms at 640x480: random numbers are drawn as raw 16-bit words in bulk and
    turned into noise with comparisons and look-up tables, never per pixel in Python (``benchmarks/noise.py``).

Quantisation: probabilities of per-pixel events (salt and pepper) and the gaussian's quantiles have a resolution of
2**-16; the gaussian noise is exact ``round(sigma * z)`` up to that resolution, with ``|z|`` at most 4.3 (a tail
of 1.5e-5 is folded back into the outermost quantile).
"""

from __future__ import annotations

import abc
import collections
import math
from collections.abc import Sequence

import cv2
import numpy as np

from protocol.episode_spec import (
    BM_NOISE_MODELS,
    Affine,
    Blur,
    Brightness,
    Daytime,
    Delay,
    Drop,
    Gaussian,
    Jpeg,
    Night,
    NoiseStage,
    Occlusion,
    SaltPepper,
)

__all__ = [
    "BlurModel",
    "BrightnessModel",
    "DelayModel",
    "DropModel",
    "GaussianModel",
    "JpegModel",
    "NoiseModel",
    "NoisePipeline",
    "OcclusionModel",
    "SaltPepperModel",
    "AlbumentationsModel",
    "BMDrawnModel",
    "MissingExtra",
    "make_model",
    "require_extras",
]

_U16_LEVELS = 1 << 16
_SMALL_IMAGE_PX = 64

Seed = int | Sequence[int]


def _seed_entropy(seed: Seed) -> list[int]:
    """Entropy words for ``np.random.SeedSequence``: any int (negative too) or a sequence of ints.

    SeedSequence only takes non-negative words, so each word is zigzag-mapped (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...),
    which keeps distinct seeds distinct.
    """
    if isinstance(seed, int | np.integer):
        words = [seed]
    elif isinstance(seed, Sequence | np.ndarray) and not isinstance(seed, str | bytes):
        words = list(seed)
    else:
        raise TypeError(f"seed must be an int or a sequence of ints, got {seed!r}")
    if not words:
        raise ValueError("seed must be an int or a non-empty sequence of ints")
    entropy = []
    for word in words:
        if not isinstance(word, int | np.integer) or isinstance(word, bool):
            raise TypeError(f"seed words must be ints, got {word!r}")
        word = int(word)
        entropy.append(2 * word if word >= 0 else -2 * word - 1)
    return entropy


def _random_u16(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` uniform 16-bit words from ``rng``'s bit generator, in bulk (under 1 ns a word).

    Raw 64-bit outputs read as little-endian 16-bit words, so the stream is the same on every machine.
    """
    raw = rng.bit_generator.random_raw((count + 3) // 4)
    return np.asarray(raw, dtype="<u8").view("<u2")[:count]


def _check_image(image_rgb: np.ndarray) -> np.ndarray:
    """The frame as a C-contiguous H x W x 3 uint8 array (no copy when it already is one); ValueError otherwise."""
    if not isinstance(image_rgb, np.ndarray):
        raise ValueError(f"image must be a NumPy array, got {type(image_rgb).__name__}")
    if image_rgb.dtype != np.uint8 or image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or 0 in image_rgb.shape:
        raise ValueError(f"image must be H x W x 3 uint8 RGB, got shape {image_rgb.shape} of {image_rgb.dtype}")
    return np.ascontiguousarray(image_rgb)


class NoiseModel(abc.ABC):
    """One perturbation stage: ``reset(seed=...)`` per episode, then ``apply(image)`` per frame."""

    stage: NoiseStage

    def __init__(self, stage: NoiseStage):
        self.stage = stage
        self.reset(seed=0)

    def reset(self, *, seed: Seed) -> None:
        """Start an episode: a fresh generator from ``seed`` (an int, or a sequence of ints as the pipeline passes
        ``(seed, stage_index)``) and no memory of earlier frames."""
        self._rng = np.random.default_rng(_seed_entropy(seed))

    @abc.abstractmethod
    def apply(self, image_rgb: np.ndarray) -> np.ndarray | None:
        """Perturb one H x W x 3 uint8 RGB frame; None: the frame is dropped. Never writes to ``image_rgb``."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.stage!r})"


class SaltPepperModel(NoiseModel):
    """Each pixel (all three channels) becomes white with probability p/2 and black with probability p/2.

    One 16-bit word per pixel: ``u < t/2`` white, ``t/2 <= u < t`` black, with ``t = round(p * 2**16)``. The result
    is ``min(max(image, white), not black)`` with 0/255 masks, all in OpenCV (about 0.5 ms at 640x480).
    """

    stage: SaltPepper

    def __init__(self, stage: SaltPepper):
        super().__init__(stage)
        self._changed_below = round(stage.probability * _U16_LEVELS)
        self._white_below = self._changed_below // 2
        self._shape: tuple[int, int] | None = None

    def _buffers(self, height: int, width: int) -> None:
        # Scratch masks, reused frame to frame (the output itself is always a new array).
        self._shape = (height, width)
        self._white = np.empty((height, width), np.uint8)
        self._keep = np.empty((height, width), np.uint8)
        self._white3 = np.empty((height, width, 3), np.uint8)
        self._keep3 = np.empty((height, width, 3), np.uint8)

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        if self._changed_below == 0:
            return image_rgb
        height, width = image.shape[:2]
        if self._shape != (height, width):
            self._buffers(height, width)
        words = _random_u16(self._rng, height * width).reshape(height, width)
        if height * width < _SMALL_IMAGE_PX:
            # OpenCV's Python binding reads arrays of up to 4 values as scalars; tiny images take NumPy's path
            out = image.copy()
            out[words < self._white_below] = 255
            out[(words >= self._white_below) & (words < self._changed_below)] = 0
            return out
        # 255 where white. OpenCV takes a scalar for src2; its stubs only list arrays.
        cv2.compare(words, self._white_below, cv2.CMP_LT, dst=self._white)  # type: ignore[call-overload]
        # 255 where kept (not black): outside [white_below, changed_below - 1]
        cv2.inRange(words, self._white_below, self._changed_below - 1, dst=self._keep)
        cv2.bitwise_not(self._keep, dst=self._keep)
        cv2.cvtColor(self._white, cv2.COLOR_GRAY2RGB, dst=self._white3)
        cv2.cvtColor(self._keep, cv2.COLOR_GRAY2RGB, dst=self._keep3)
        out = cv2.max(image, self._white3)
        cv2.min(out, self._keep3, dst=out)
        return out


class GaussianModel(NoiseModel):
    """Adds ``round(sigma * z)`` per channel, z standard normal, clipped to 0..255.

    z comes from one 16-bit word per channel value through a 65536-entry table of integer quantiles
    (``round(sigma * ndtri((i + 0.5) / 2**16))``): three times faster than NumPy's float normals, and exact after
    the rounding to integers that the uint8 output needs anyway, up to the 2**-16 quantile resolution.
    """

    stage: Gaussian

    def __init__(self, stage: Gaussian):
        super().__init__(stage)
        from scipy.special import ndtri  # lazy: only runs that use gaussian noise pay for scipy's import

        quantiles = ndtri((np.arange(_U16_LEVELS, dtype=np.float64) + 0.5) / _U16_LEVELS)
        with np.errstate(invalid="ignore", over="ignore"):
            # noise beyond +-255 saturates every pixel anyway, so clipping the table there changes nothing
            table = np.clip(np.rint(stage.sigma * quantiles), -255, 255)
        self._table = table.astype(np.int16)
        self._noise: np.ndarray | None = None

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        if self.stage.sigma == 0:
            return image_rgb
        if self._noise is None or self._noise.shape != image.shape:
            self._noise = np.empty(image.shape, np.int16)
        words = _random_u16(self._rng, image.size).reshape(image.shape)
        np.take(self._table, words, out=self._noise, mode="clip")  # words < 2**16: "clip" only skips the check
        return cv2.add(image, self._noise, dtype=cv2.CV_8U)  # saturating: clipped to 0..255


class BlurModel(NoiseModel):
    """OpenCV Gaussian blur, ``kernel_px`` square, sigma from the kernel size by OpenCV's rule
    (``0.3 * ((k - 1) / 2 - 1) + 0.8``), borders reflected (BORDER_REFLECT_101). Deterministic."""

    stage: Blur

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        size = self.stage.kernel_px
        if size == 1:
            return image_rgb
        return cv2.GaussianBlur(image, (size, size), 0, borderType=cv2.BORDER_REFLECT_101)


class BrightnessModel(NoiseModel):
    """``out = contrast * (in - 128) + 128 + 255 * brightness``, rounded to the nearest integer (ties to even),
    clipped to 0..255; one 256-entry look-up table. Deterministic."""

    stage: Brightness

    def __init__(self, stage: Brightness):
        super().__init__(stage)
        if not math.isfinite(stage.contrast):  # the struct lets NaN and inf through; inf * 0 has no meaning here
            raise ValueError(f"brightness contrast must be finite, got {stage.contrast}")
        levels = np.arange(256, dtype=np.float64)
        values = stage.contrast * (levels - 128.0) + 128.0 + 255.0 * stage.brightness
        self._lut = np.clip(np.rint(values), 0, 255).astype(np.uint8)
        self._identity = bool(np.array_equal(self._lut, np.arange(256, dtype=np.uint8)))

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        if self._identity:
            return image_rgb
        return cv2.LUT(image, self._lut)


class OcclusionModel(NoiseModel):
    """With ``probability`` per frame, ``patches`` black rectangles of ``round(size_fraction * H)`` rows by
    ``round(size_fraction * W)`` columns (at least 1 px), each placed uniformly at random wholly inside the image.

    Patches are independent and may overlap, so the covered fraction is ``patches * size_fraction**2`` at most
    (about 0.078 rather than 0.08 on average for 2 x 0.2). One uniform draw per frame decides whether it fires,
    then two integers per patch when it does.
    """

    stage: Occlusion

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        stage = self.stage
        if stage.patches == 0 or stage.probability == 0.0:
            return image_rgb
        if self._rng.random() >= stage.probability:
            return image_rgb
        height, width = image.shape[:2]
        patch_h = min(height, max(1, round(stage.size_fraction * height)))
        patch_w = min(width, max(1, round(stage.size_fraction * width)))
        tops = self._rng.integers(0, height - patch_h + 1, size=stage.patches)
        lefts = self._rng.integers(0, width - patch_w + 1, size=stage.patches)
        out = image.copy()
        for top, left in zip(tops.tolist(), lefts.tolist(), strict=True):
            out[top : top + patch_h, left : left + patch_w] = 0
        return out


class JpegModel(NoiseModel):
    """JPEG encode then decode at ``quality`` with OpenCV's libjpeg (RGB converted to BGR for the encoder, so the
    chroma subsampling sees the right colours). Deterministic; lossy even at quality 100."""

    stage: Jpeg

    def __init__(self, stage: Jpeg):
        super().__init__(stage)
        self._params = [cv2.IMWRITE_JPEG_QUALITY, int(stage.quality)]
        self._decode_rgb = getattr(cv2, "IMREAD_COLOR_RGB", None)  # OpenCV >= 4.10 decodes straight to RGB

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), self._params)
        if not ok:
            raise RuntimeError(f"OpenCV failed to JPEG-encode a {image.shape} image")
        if self._decode_rgb is not None:
            decoded = cv2.imdecode(encoded, self._decode_rgb)
        else:
            bgr = cv2.imdecode(encoded, cv2.IMREAD_COLOR)  # None when it fails: the check below says so
            decoded = None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        if decoded is None or decoded.shape != image.shape:
            raise RuntimeError(f"OpenCV failed to decode its own JPEG of a {image.shape} image")
        return decoded


class DelayModel(NoiseModel):
    """The brain sees the frame of ``frames`` frames earlier; during the first ``frames`` frames of an episode, the
    oldest one buffered (the episode's first frame).

    Buffers read-only copies (the caller may reuse its input array; a copy costs about 0.05 ms at 640x480) and
    returns them as they are, so the first frame comes out ``frames + 1`` times as the same object.
    ``apply(None)`` records a frame lost upstream (see ``NoisePipeline``): it comes out ``frames`` frames later as
    ``None``, so the buffer advances once per camera frame, dropped or not. Deterministic.
    """

    stage: Delay

    def __init__(self, stage: Delay):
        self._buffer: collections.deque[np.ndarray | None] = collections.deque()
        super().__init__(stage)

    def reset(self, *, seed: Seed) -> None:
        super().reset(seed=seed)
        self._buffer.clear()

    def apply(self, image_rgb: np.ndarray | None) -> np.ndarray | None:
        if image_rgb is not None:
            _check_image(image_rgb)
        if self.stage.frames == 0:
            return image_rgb
        if image_rgb is not None:
            image_rgb = np.array(image_rgb, dtype=np.uint8, order="C", copy=True)
            image_rgb.flags.writeable = False
        self._buffer.append(image_rgb)
        out = self._buffer[0]
        if len(self._buffer) > self.stage.frames:
            self._buffer.popleft()
        return out


class DropModel(NoiseModel):
    """Drops a frame (returns None) with ``probability``, else returns the input object itself. One uniform draw
    per frame, whatever the probability."""

    stage: Drop

    def apply(self, image_rgb: np.ndarray) -> np.ndarray | None:
        _check_image(image_rgb)
        if self._rng.random() < self.stage.probability:
            return None
        return image_rgb


class MissingExtra(ValueError):
    """A noise model needs a package that is not installed (one line naming the extra that brings it)."""


_BM_MIN_PX = 32  # smaller frames (tests' tiny images, not cameras) are perturbed on a canvas this big
BM_EXTRA_HINT = "pip install 'drivebench[bm]' (scripts/setup.sh installs it)"


# BM's perturbations that albumentations 2.x draws exactly as 1.0.3 did (measured: benchmarks/bm_perturbations.py);
# the others are drawn by services.noise.bm and need nothing more.
_ALBUMENTATIONS_STAGES: tuple[type[NoiseStage], ...] = (Night, Daytime, Affine)


def require_extras(stages: Sequence[NoiseStage]) -> None:
    """:class:`MissingExtra` when a stage needs albumentations and it is not installed, before anything starts."""
    import importlib.util

    needing = [str(type(stage).__struct_config__.tag) for stage in stages if isinstance(stage, _ALBUMENTATIONS_STAGES)]
    if needing and importlib.util.find_spec("albumentations") is None:
        raise MissingExtra(f"noise model {needing[0]} needs albumentations: {BM_EXTRA_HINT}")


def _albumentations():
    """albumentations, imported on first use (seconds: scipy, pydantic), without its network check for updates."""
    import os
    import sys

    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")  # it would ask PyPI at import time, from every process
    # Its package imports its torch helpers, and so torch where installed: 8 of 11 s of the import measured on a
    # loaded 2-core machine, paid by an episode's first perturbed frame. None of BM's perturbations needs them.
    blocked = "albumentations" not in sys.modules and "albumentations.pytorch" not in sys.modules
    if blocked:
        sys.modules["albumentations.pytorch"] = None  # importing it now raises ImportError
    try:
        import albumentations
    except ImportError:
        raise MissingExtra(f"Behavior Metrics' perturbations need albumentations: {BM_EXTRA_HINT}") from None
    finally:
        if blocked:
            del sys.modules["albumentations.pytorch"]  # a brain that imports it later gets it, torch and all
    return albumentations


def _bm_transform(stage: NoiseStage):
    """The albumentations transform of night, daytime or affine, with BM's parameters; always applied (BM's
    ``always_apply=True``)."""
    A = _albumentations()  # the library's usual name
    if isinstance(stage, Night | Daytime):
        shift = -0.5 if isinstance(stage, Night) else 0.3
        return A.RandomBrightnessContrast(brightness_limit=(shift, shift), contrast_limit=(0.0, 0.0), p=1.0)
    if isinstance(stage, Affine):
        return A.Affine(translate_percent={"x": -0.1, "y": 0.0}, p=1.0)
    raise TypeError(f"not one of Behavior Metrics' albumentations perturbations: {stage!r}")


class AlbumentationsModel(NoiseModel):
    """Behavior Metrics' night, daytime or affine through albumentations, as BM's ``transform_image`` applies them
    (deterministic: they draw nothing at random; the seed is passed on all the same)."""

    def __init__(self, stage: NoiseStage):
        self._compose = _albumentations().Compose([_bm_transform(stage)])
        super().__init__(stage)

    def reset(self, *, seed: Seed) -> None:
        super().reset(seed=seed)
        state = np.random.SeedSequence(_seed_entropy(seed)).generate_state(1)[0]
        self._compose.set_random_seed(int(state))

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb)
        height, width = image.shape[:2]
        if min(height, width) < _BM_MIN_PX:  # tiny frames: perturb a padded canvas, crop it back
            pad_y, pad_x = max(0, _BM_MIN_PX - height), max(0, _BM_MIN_PX - width)
            canvas = cv2.copyMakeBorder(image, 0, pad_y, 0, pad_x, cv2.BORDER_REPLICATE)
            return np.ascontiguousarray(self._compose(image=canvas)["image"][:height, :width], dtype=np.uint8)
        return np.ascontiguousarray(self._compose(image=image)["image"], dtype=np.uint8)


class BMDrawnModel(NoiseModel):
    """Behavior Metrics' rain, shadow, snow, fog or sunflare, drawn by ``services.noise.bm`` as albumentations 1.0.3
    draws them, from this model's seeded generator. Costs a few ms a frame at 640x480, fog and sunflare the most
    (``benchmarks/noise.py``)."""

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        from services.noise.bm import DRAWS

        image = _check_image(image_rgb)
        return DRAWS[str(type(self.stage).__struct_config__.tag)](image, self._rng)


_MODELS: dict[type, type[NoiseModel]] = {
    **{model: AlbumentationsModel for model in _ALBUMENTATIONS_STAGES},
    **{model: BMDrawnModel for model in BM_NOISE_MODELS if model not in _ALBUMENTATIONS_STAGES},
    SaltPepper: SaltPepperModel,
    Gaussian: GaussianModel,
    Blur: BlurModel,
    Brightness: BrightnessModel,
    Occlusion: OcclusionModel,
    Jpeg: JpegModel,
    Delay: DelayModel,
    Drop: DropModel,
}


def make_model(stage: NoiseStage) -> NoiseModel:
    """The model of one noise stage struct (seeded with 0 until ``reset``); TypeError for anything else."""
    try:
        model_class = _MODELS[type(stage)]
    except KeyError:
        raise TypeError(
            f"not a noise stage: {stage!r} (expected one of {', '.join(t.__name__ for t in _MODELS)})"
        ) from None
    return model_class(stage)


class NoisePipeline:
    """The stages of ``EpisodeSpec.noise``, applied in order to each camera frame.

    ``reset(seed=...)`` seeds stage ``i`` from ``(seed, i)``: each stage has its own independent generator, so
    appending a stage leaves the others' randomness as it was.

    Drops: once a stage drops a frame, the stages after it are not applied, except Delay stages, which are told
    (``apply(None)``) so that their buffer still advances once per camera frame: Delay(k) always means k camera
    frames (k * step_s of latency), and a frame lost before a delay is lost k frames later, as on a real link
    where a frame lost at the camera is also missing from the delayed stream. A delayed frame that comes out of the
    buffer goes through the stages after the Delay. So ``[Drop(p), Delay(k)]`` and ``[Delay(k), Drop(p)]`` behave
    alike (the same statistics, not the same random draws). Stages skipped for a dropped frame draw no random
    numbers for it, which is still deterministic: the drop decisions themselves are seeded.

    With no stages, ``apply`` returns its input object as it is, at no cost.
    """

    def __init__(self, stages: Sequence[NoiseStage]):
        self.stages: tuple[NoiseStage, ...] = tuple(stages)
        self.models: tuple[NoiseModel, ...] = tuple(make_model(stage) for stage in self.stages)
        self.reset(seed=0)

    def reset(self, *, seed: int) -> None:
        """Start an episode: stage ``i`` gets a fresh generator from ``(seed, i)``; Delay buffers are emptied."""
        _seed_entropy(seed)  # fails here, naming the pipeline's seed, rather than in a stage
        for index, model in enumerate(self.models):
            model.reset(seed=(seed, index))

    def apply(self, image_rgb: np.ndarray) -> np.ndarray | None:
        """The perturbed frame, or None when it is dropped. Never writes to ``image_rgb``."""
        image: np.ndarray | None = image_rgb
        for model in self.models:
            if image is not None:
                image = model.apply(image)
            elif isinstance(model, DelayModel):
                image = model.apply(None)
        return image

    def __len__(self) -> int:
        return len(self.models)

    def __repr__(self) -> str:
        return f"NoisePipeline({list(self.stages)!r})"
