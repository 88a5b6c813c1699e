"""The paper's trained networks as brains: camera frames -> history window -> network -> (speed, yaw rate).

``python -m brains --brain memdccp --weights CKPT`` (or ``--set options.weights=CKPT``). Options:

* ``weights``: a ``drivebench.checkpoint.v1`` file (see :mod:`brains.neural.checkpoint`), or an ONNX file written
  by ``drivebench export`` (self-describing through its metadata; served with onnxruntime alone, no torch).
* ``backend``: ``onnx`` (default; onnxruntime, 1.5-7x faster than eager PyTorch on CPU) or ``torch`` (eager).
* ``threads``: intra-op threads (1 by default: the brain shares the cores with the simulator).
* ``device``: where the torch backend runs: ``cpu`` (default), ``cuda``, ``cuda:N``, or ``auto`` (CUDA when there
  is one). The compose service ``brain-gpu`` sets ``backend=torch device=cuda``.
* ``onnx_path``: where the ONNX export of a checkpoint lives; reused if it exists (it must come from the same
  checkpoint), written there otherwise. Without it the export goes to a temporary file, deleted once loaded.

**History.** Checkpoints give the input frames as offsets from the current frame. They count frames at the
*training* step, but the run-time step may differ, so serving uses the offsets in seconds: for each offset the
brain takes the stored frame whose stamp is closest to ``stamp + offset_s`` (ties: the older frame). Until the
history is long enough the oldest frame of the episode stands in (clamped at the episode start): every frame is
answered from the first one on, where Behavior Metrics' brain sent nothing for its first 9 iterations. A frame the
host never passed on (dropped by the noise injector) simply is not in the history; the closest stamp still wins.
``reset`` clears the history. Frames are stored preprocessed, so each is cropped/resized/normalised once.
"""

from __future__ import annotations

import logging
import tempfile
from collections import deque
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from brains.base import Action, Observation
from brains.nets import MODELS
from brains.neural.checkpoint import (
    Checkpoint,
    CheckpointError,
    InputSpec,
    Normalisation,
    from_metadata,
    load_checkpoint,
)
from brains.neural.export import SOURCE_SHA256_KEY, export_onnx, file_sha256
from brains.neural.runners import OrtRunner, TorchRunner
from brains.registry import BrainOptionsError, shipped_weights

log = logging.getLogger("drivebench.brain.neural")

BACKENDS = ("onnx", "torch")


# -- preprocessing ---------------------------------------------------------------------------------------------------


class Preprocessor:
    """Camera frame (H, W, 3) uint8 RGB -> (3, height_px, width_px) float32, exactly as the dataset shapes frames:
    keep rows [round(top * H), round(bottom * H)), cv2.resize INTER_AREA, / 255, (x - mean) / std, HWC -> CHW."""

    def __init__(self, spec: InputSpec, norm: Normalisation):
        self.spec = spec
        self._mean = np.asarray(norm.image_mean, dtype=np.float32)
        self._std = np.asarray(norm.image_std, dtype=np.float32)

    def __call__(self, image_rgb: np.ndarray) -> np.ndarray:
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) RGB frame, got shape {image_rgb.shape}")
        height = image_rgb.shape[0]
        top, bottom = round(self.spec.crop_top_fraction * height), round(self.spec.crop_bottom_fraction * height)
        if bottom <= top:
            raise ValueError(
                f"crop {self.spec.crop_top_fraction}..{self.spec.crop_bottom_fraction} keeps no row "
                f"of a {height}-row frame"
            )
        resized = cv2.resize(
            image_rgb[top:bottom], (self.spec.width_px, self.spec.height_px), interpolation=cv2.INTER_AREA
        )
        # The same float32 operations, in the same order, as the training pipeline (not folded into one
        # multiply-add, which would differ in the last bits).
        x = (resized.astype(np.float32) / np.float32(255.0) - self._mean) / self._std
        return np.ascontiguousarray(x.transpose(2, 0, 1))


# -- the brain -------------------------------------------------------------------------------------------------------


class NeuralBrain:
    """A trained network driving from the camera (see the module docstring for options and the history rule).

    weights: checkpoint file (``.pt``/anything torch.load reads) or ONNX file from ``drivebench export``.
    backend: "onnx" or "torch". threads: intra-op threads (>= 1). onnx_path: ONNX export cache (checkpoints only).
    model: if given, the network the weights must hold (the named brains set it).
    """

    def __init__(
        self,
        *,
        weights: str,
        backend: str = "onnx",
        threads: int = 1,
        onnx_path: str | None = None,
        model: str | None = None,
        device: str = "cpu",
    ):
        if backend not in BACKENDS:
            raise BrainOptionsError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        if device != "cpu" and backend != "torch":
            raise BrainOptionsError(f"device {device!r} needs backend torch (the onnx backend runs on the CPU)")
        if not isinstance(threads, int) or threads < 1:
            raise BrainOptionsError(f"threads must be an integer >= 1, got {threads!r}")
        path = Path(weights)
        if path.suffix.lower() == ".onnx":
            self.checkpoint, self._run = _serve_onnx_file(path, backend=backend, threads=threads, model=model)
        else:
            self.checkpoint = load_checkpoint(path)
            _check_model(self.checkpoint, model)
            self._run = _backend(self.checkpoint, backend=backend, threads=threads, onnx_path=onnx_path, device=device)
        self.backend = backend
        # BM's gpu_inference: whether the model runs on a GPU (the host puts it in every command)
        self.gpu_inference = getattr(getattr(self._run, "device", None), "type", "cpu") == "cuda"
        self.preprocess = Preprocessor(self.checkpoint.input, self.checkpoint.normalisation)
        self._offsets_ns = [round(o * 1e9) for o in self.checkpoint.input.offsets_s]
        self._label_mean = np.asarray(self.checkpoint.normalisation.label_mean, dtype=np.float64)
        self._label_std = np.asarray(self.checkpoint.normalisation.label_std, dtype=np.float64)
        self.history: deque[tuple[int, np.ndarray]] = deque()  # (stamp_ns, preprocessed (3, H, W)), oldest first

    def reset(self, *, seed: int) -> None:
        """Forget the previous episode's frames (the networks are deterministic: ``seed`` is unused)."""
        del seed
        self.history.clear()

    def act(self, observation: Observation) -> Action:
        self._remember(observation.stamp_ns, self.preprocess(observation.image_rgb))
        v_n, w_n = self._run(self.model_input())[0]
        v, w = np.array([v_n, w_n], dtype=np.float64) * self._label_std + self._label_mean
        return Action(speed_mps=float(v), yaw_rate_radps=float(w))

    # -- history ---

    def _remember(self, stamp_ns: int, frame: np.ndarray) -> None:
        if self.history and stamp_ns <= self.history[-1][0]:
            # Stamps restart only with a new episode, which the host announces with reset(): be safe anyway.
            log.warning("frame stamp %d ns not after the previous one: starting a new history", stamp_ns)
            self.history.clear()
        self.history.append((stamp_ns, frame))
        # A frame with a newer one at or before the oldest target can never be the closest again (targets only
        # move forward): drop it, so the history holds about span / step + 1 frames.
        oldest_target = stamp_ns + self._offsets_ns[0]
        while len(self.history) >= 2 and self.history[1][0] <= oldest_target:
            self.history.popleft()

    def _selected(self) -> list[tuple[int, np.ndarray]]:
        if not self.history:
            raise RuntimeError("no frame yet: call act() first")
        now = self.history[-1][0]
        return [
            min(self.history, key=lambda item: (abs(item[0] - (now + offset)), item[0])) for offset in self._offsets_ns
        ]

    def input_stamps_ns(self) -> list[int]:
        """Stamps (ns) of the frames the next network input is built from, oldest offset first."""
        return [stamp for stamp, _ in self._selected()]

    def model_input(self) -> np.ndarray:
        """The network input for the newest frame: float32 (1, 3, H, W), or (1, T, 3, H, W) oldest first."""
        frames = [frame for _, frame in self._selected()]
        batch = frames[0][None] if len(frames) == 1 else np.stack(frames)[None]
        return np.ascontiguousarray(batch, dtype=np.float32)


def _check_model(ckpt: Checkpoint, model: str | None) -> None:
    if model is not None and ckpt.model != model:
        raise CheckpointError(f"{ckpt.path}: holds a {ckpt.model} network, not {model}")


def _serve_onnx_file(path: Path, *, backend: str, threads: int, model: str | None) -> tuple[Checkpoint, OrtRunner]:
    if backend != "onnx":
        raise CheckpointError(f"{path}: an ONNX file serves with backend 'onnx' only, not {backend!r}")
    if not path.is_file():
        raise CheckpointError(f"{path}: no such ONNX file")
    runner = OrtRunner(path, threads=threads)
    ckpt = from_metadata(runner.metadata(), path)
    _check_model(ckpt, model)
    return ckpt, runner


def _backend(ckpt: Checkpoint, *, backend: str, threads: int, onnx_path: str | None, device: str = "cpu"):
    if backend == "torch":
        return TorchRunner(ckpt, threads=threads, device=device)
    if onnx_path is None:
        with tempfile.TemporaryDirectory(prefix="drivebench-onnx-") as folder:
            # The session keeps the model in memory: the file can go as soon as it is loaded.
            return OrtRunner(export_onnx(ckpt.path, Path(folder) / "model.onnx", ckpt=ckpt), threads=threads)
    path = Path(onnx_path)
    if not path.is_file():
        export_onnx(ckpt.path, path, ckpt=ckpt)
        return OrtRunner(path, threads=threads)
    runner = OrtRunner(path, threads=threads)
    if runner.metadata().get(SOURCE_SHA256_KEY) != file_sha256(ckpt.path):
        raise CheckpointError(
            f"{path}: exported from another checkpoint than {ckpt.path}; delete it or set another onnx_path"
        )
    return runner


# -- registry factories ----------------------------------------------------------------------------------------------


class _Factory:
    """The registry's factory for brain ``brain``: ``NeuralBrain`` over any network (``model`` None) or one network
    (``model``: its name, which a checkpoint must hold). A class rather than a function with attributes, so that
    ``preflight`` (``brains.registry.preflight`` calls it) is part of its type."""

    def __init__(self, brain: str, model: str | None):
        self._brain = brain
        self._model = model
        self.__name__ = self.__qualname__ = brain
        self.__doc__ = f"Brain {brain!r}: NeuralBrain(weights=..., ...)" + (
            f" serving a {model} checkpoint." if model else " serving any network."
        )

    def _weights(self, weights: str | None) -> str:
        if not weights and (shipped := shipped_weights(self._brain)) is not None:
            return str(shipped)  # the network drivebench ships weights for
        if not weights:
            raise BrainOptionsError(f"brain {self._brain!r} needs --weights CKPT (or --set options.weights=CKPT)")
        return weights

    def __call__(self, *, weights: str | None = None, **options: Any) -> NeuralBrain:
        if not weights:
            weights = self._weights(weights)
            log.info("no weights given: serving the shipped %s", weights)
        if self._model is not None:
            options["model"] = self._model
        return NeuralBrain(weights=weights, **options)

    def preflight(self, *, weights: str | None = None, **options: Any) -> None:
        """Check the weights before any process starts, the shipped ones too (their shards are read and verified):
        loadable, the right network (CheckpointError or BrainOptionsError, one line)."""
        path = Path(self._weights(weights))
        if path.suffix.lower() == ".onnx":  # the same rule and checks as NeuralBrain's; one thread is enough here
            _serve_onnx_file(path, backend=options.get("backend", "onnx"), threads=1, model=self._model)
        else:
            _check_model(load_checkpoint(path), self._model)


neural = _Factory("neural", None)
_NETWORK_FACTORIES: dict[str, _Factory] = {}


def __getattr__(name: str) -> _Factory:
    """``brains.neural.brain.<network>``: the brain factory of every network in ``brains.nets.MODELS``, made on
    first use, so that a new network folder is a brain with no line here (PEP 562 module attribute)."""
    if name not in MODELS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return _NETWORK_FACTORIES.setdefault(name, _Factory(name, name))
