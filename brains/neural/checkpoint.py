"""Trained-network checkpoints (``drivebench.checkpoint.v1``): load, check, build the model; torch only when needed.

A checkpoint is a ``torch.save`` dict, loadable with ``torch.load(path, weights_only=True)``::

    {"format": "drivebench.checkpoint.v1", "model": "memdccp", "hyper": {...},   # make_model(model, **hyper)
     "state_dict": {...},
     "input": {"width_px": 100, "height_px": 50, "crop_top_fraction": 0.0, "crop_bottom_fraction": 1.0,
               "offsets_frames": [-9, -5, 0], "offsets_s": [-0.45, -0.25, 0.0], "step_s": 0.05},
     "normalisation": {"image_mean": [3], "image_std": [3], "labels": "zscore" | "paper",
                       "label_mean": [m_v, m_w], "label_std": [s_v, s_w]},          # y = y_n * std + mean
     "dataset": {...}, "metrics": {...}, "training": {...}}

The training code writes these; this module reads them for serving (and writes them for tests and smoke runs).

Packed form (:func:`pack_checkpoint`, ``drivebench pack``): small enough for git (PilotNet's 68 MB of float32
weights become ~34 MB of float16 in files of at most 9 MiB each). ``model.ckpt`` is the same dict without
resume-only state and with an empty ``state_dict``, plus::

    "state_dict_shards": {"files": ["model.ckpt.shard0", ...],  # beside model.ckpt, joined in this order
                          "sha256": hex of the joined bytes, "file_sha256": [hex per file],
                          "dtype": "float16" | "float32", "bytes": total}

The joined shard bytes are a ``torch.save`` of the state dict (floating tensors in ``dtype``; integer buffers as
they were). :func:`read_checkpoint` joins and verifies them and casts floating tensors back to float32, so
everything downstream (serving, export, the paper's tables) sees an ordinary checkpoint.

The same description (model, hyper, input, normalisation) travels in an exported ONNX file's metadata, so an ONNX
file is self-describing: :func:`to_metadata` / :func:`from_metadata`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from brains.nets import MODELS
from brains.registry import BrainOptionsError

FORMAT = "drivebench.checkpoint.v1"
ONNX_FORMAT = "drivebench.onnx.v1"
LABEL_MODES = ("zscore", "paper")
# What every checkpoint must hold (extra keys, e.g. a resumable run's optimizer state, are allowed).
REQUIRED_KEYS = {
    "": ("format", "model", "hyper", "state_dict", "input", "normalisation", "dataset", "metrics", "training"),
    "input": (
        "width_px",
        "height_px",
        "crop_top_fraction",
        "crop_bottom_fraction",
        "offsets_frames",
        "offsets_s",
        "step_s",
    ),
    "normalisation": ("image_mean", "image_std", "labels", "label_mean", "label_std"),
}


# What a packed checkpoint keeps: enough to serve, export and report; optimizer, rng and resume state are dropped.
PACKED_KEYS = ("format", "model", "hyper", "input", "normalisation", "dataset", "metrics", "training")
SHARDS_KEY = "state_dict_shards"
LFS_POINTER_PREFIX = b"version https://git-lfs"


class CheckpointError(BrainOptionsError):
    """A checkpoint (or exported ONNX file) that cannot be served: one line naming the file and the problem."""


@dataclass(frozen=True)
class InputSpec:
    """How camera frames become the network's input.

    width_px, height_px: network image size after resizing.
    crop_top_fraction, crop_bottom_fraction: rows [top, bottom) of the camera frame kept, as fractions of its height.
    offsets_frames: history offsets in frames at the training step ``step_s``, increasing, ending at 0.
    offsets_s: the same offsets in seconds (what serving uses: the run-time step may differ).
    step_s: the training recordings' step, s (None if they mixed steps).
    """

    width_px: int
    height_px: int
    crop_top_fraction: float
    crop_bottom_fraction: float
    offsets_frames: tuple[int, ...]
    offsets_s: tuple[float, ...]
    step_s: float | None


@dataclass(frozen=True)
class Normalisation:
    """Pixel normalisation (per RGB channel, on [0, 1] pixels) and label de-normalisation ``y = y_n * std + mean``.

    label_mean, label_std: (v m/s, w rad/s). ``labels`` says how they were chosen ("zscore": training-split
    statistics; "paper": DLS's fixed ranges, mean (6.5, -7.1), std (17.5, 14.2)); serving treats both alike.
    """

    image_mean: tuple[float, float, float]
    image_std: tuple[float, float, float]
    labels: str
    label_mean: tuple[float, float]
    label_std: tuple[float, float]


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint. ``state_dict`` is None when the description came from an ONNX file's metadata."""

    path: Path
    model: str
    hyper: dict[str, Any]
    state_dict: dict[str, Any] | None
    input: InputSpec
    normalisation: Normalisation
    dataset: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        """Frames per network input: 1 -> input (B, 3, H, W); more -> (B, T, 3, H, W), oldest first."""
        return len(self.input.offsets_s)


# -- reading ---------------------------------------------------------------------------------------------------------


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Load and check a checkpoint file; CheckpointError (one line) for a missing file, a file that is not a
    drivebench checkpoint, another format version, missing keys, an unknown model or malformed input/normalisation
    fields."""
    path = Path(path)
    return _parse(read_checkpoint(path), path)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint as the plain dict ``torch.save`` wrote (training resumes from it), after the same checks as
    :func:`load_checkpoint` except the typed parsing of input and normalisation. A packed checkpoint comes back with
    its shards joined, verified and cast to float32 in ``state_dict`` (CheckpointError, one line naming the shard
    file, for a missing or changed shard)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    import torch  # only here: reading ONNX metadata or preprocessing must not need torch

    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises UnpicklingError, RuntimeError, EOFError... for non-checkpoints
        # Never pass on torch's advice to load with weights_only=False: that runs whatever the file contains. What
        # the file holds decides which mistake it is (torch reads its pickle without running it), not torch's words.
        if unsafe := _unsafe_globals(path):
            raise CheckpointError(
                f"{path}: not a torch checkpoint of tensors and plain data (the only kind drivebench loads; it holds "
                f"{unsafe[0]})"
            ) from None
        # torch's UnpicklingError carries that advice: say what failed, not its words.
        why = "its pickle is not one of tensors and plain data" if isinstance(error, pickle.UnpicklingError) else None
        raise CheckpointError(f"{path}: not a torch checkpoint ({why or _first_line(error)})") from None
    _check_keys(raw, path)
    if isinstance(raw, dict) and SHARDS_KEY in raw:
        raw["state_dict"] = _read_shards(raw[SHARDS_KEY], path)
    return raw


def _unsafe_globals(path: Path) -> list[str]:
    """The functions and classes a torch checkpoint's pickle names beyond tensors and plain data (read statically,
    nothing run); none for a file that is not a torch checkpoint at all."""
    import torch

    try:
        return list(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception:  # not a torch zip file (random bytes, truncated): it names nothing
        return []


def _read_shards(shards: Any, path: Path) -> dict[str, Any]:
    """The state dict of a packed checkpoint: its shard files joined, verified, loaded and cast to float32."""
    import torch

    try:
        names = [str(name) for name in shards["files"]]
        expected = str(shards["sha256"])
        per_file = shards.get("file_sha256")
    except (AttributeError, KeyError, TypeError) as error:
        raise CheckpointError(f"{path}: malformed {SHARDS_KEY} entry ({_first_line(error)})") from None
    if not names or any(Path(name).name != name or name in (".", "..") for name in names):
        raise CheckpointError(f"{path}: {SHARDS_KEY} must name shard files beside it, got {names}")
    blocks = []
    for i, name in enumerate(names):
        shard = path.parent / name
        if not shard.is_file():
            raise CheckpointError(f"{path}: shard file {shard} is missing")
        block = shard.read_bytes()
        if block.startswith(LFS_POINTER_PREFIX):
            raise CheckpointError(f"{path}: shard file {shard} is a git LFS pointer, not the data (git lfs pull?)")
        if per_file is not None and i < len(per_file) and hashlib.sha256(block).hexdigest() != per_file[i]:
            raise CheckpointError(
                f"{path}: shard file {shard} does not match its sha256 (a truncated or changed copy?)"
            )
        blocks.append(block)
    data = b"".join(blocks)
    if hashlib.sha256(data).hexdigest() != expected:
        raise CheckpointError(
            f"{path}: its shards {', '.join(names)} do not match the recorded sha256 (a git LFS "
            f"pointer, a truncated copy or a shard of another pack?)"
        )
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as error:
        raise CheckpointError(f"{path}: its shards hold no torch state dict ({_first_line(error)})") from None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(f"{path}: its shards hold no torch state dict")
    return {k: v.float() if v.is_floating_point() else v for k, v in state.items()}


def _check_keys(raw: Any, path: Path) -> None:
    if not isinstance(raw, dict) or "format" not in raw:
        raise CheckpointError(f"{path}: not a drivebench checkpoint (no 'format' entry)")
    if raw["format"] != FORMAT:
        raise CheckpointError(f"{path}: format {raw['format']!r}, expected {FORMAT!r}")
    missing = [key for key in REQUIRED_KEYS[""] if key not in raw]
    for section in ("input", "normalisation"):
        if isinstance(raw.get(section), dict):
            missing += [f"{section}.{key}" for key in REQUIRED_KEYS[section] if key not in raw[section]]
        elif section in raw:
            missing.append(f"{section} (not a dict)")
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}")
    if raw["model"] not in MODELS:
        raise CheckpointError(f"{path}: unknown model {raw['model']!r} (known: {', '.join(sorted(MODELS))})")


def _parse(raw: dict[str, Any], path: Path) -> Checkpoint:
    model = raw["model"]
    try:
        spec = _input_spec(raw["input"])
        norm = _normalisation(raw["normalisation"])
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: bad input/normalisation: {_first_line(error)}") from None
    if len(spec.offsets_s) != MODELS[model].frames:
        raise CheckpointError(
            f"{path}: {len(spec.offsets_s)} frame offsets, but {model} takes {MODELS[model].frames} frame(s)"
        )
    return Checkpoint(
        path=path,
        model=model,
        hyper=dict(raw.get("hyper") or {}),
        state_dict=raw["state_dict"],
        input=spec,
        normalisation=norm,
        dataset=dict(raw.get("dataset") or {}),
        metrics=dict(raw.get("metrics") or {}),
        training=dict(raw.get("training") or {}),
    )


def _input_spec(d: dict[str, Any]) -> InputSpec:
    frames = tuple(int(o) for o in d["offsets_frames"])
    step_s = None if d.get("step_s") is None else float(d["step_s"])
    if d.get("offsets_s") is not None:
        seconds = tuple(float(o) for o in d["offsets_s"])
    elif step_s is not None or frames == (0,):
        seconds = tuple(o * (step_s or 0.0) for o in frames)
    else:
        raise ValueError("offsets_s and step_s are both missing")
    if (
        len(seconds) != len(frames)
        or not seconds
        or seconds[-1] != 0.0
        or any(b <= a for a, b in zip(seconds, seconds[1:]))
    ):
        raise ValueError(f"offsets_s {list(seconds)} must match offsets_frames {list(frames)}, increase and end at 0")
    spec = InputSpec(
        width_px=int(d["width_px"]),
        height_px=int(d["height_px"]),
        crop_top_fraction=float(d["crop_top_fraction"]),
        crop_bottom_fraction=float(d["crop_bottom_fraction"]),
        offsets_frames=frames,
        offsets_s=seconds,
        step_s=step_s,
    )
    if not 0.0 <= spec.crop_top_fraction < spec.crop_bottom_fraction <= 1.0:
        raise ValueError(f"crop {spec.crop_top_fraction}..{spec.crop_bottom_fraction} keeps no rows")
    if spec.width_px < 1 or spec.height_px < 1:
        raise ValueError(f"image size {spec.width_px}x{spec.height_px}")
    return spec


def _normalisation(d: dict[str, Any]) -> Normalisation:
    norm = Normalisation(
        image_mean=_rgb(d["image_mean"]),
        image_std=_rgb(d["image_std"]),
        labels=str(d["labels"]),
        label_mean=_pair(d["label_mean"]),
        label_std=_pair(d["label_std"]),
    )
    if norm.labels not in LABEL_MODES:
        raise ValueError(f"labels {norm.labels!r}, expected one of {', '.join(LABEL_MODES)}")
    if not all(s > 0 for s in norm.image_std + norm.label_std):
        raise ValueError("standard deviations must be > 0")
    return norm


def _floats(values: Any, n: int) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise ValueError(f"expected {n} finite numbers, got {values!r}")
    return out


def _rgb(values: Any) -> tuple[float, float, float]:
    """Three finite numbers, one per RGB channel."""
    red, green, blue = _floats(values, 3)
    return red, green, blue


def _pair(values: Any) -> tuple[float, float]:
    """Two finite numbers, one per label (v, w)."""
    speed, yaw_rate = _floats(values, 2)
    return speed, yaw_rate


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


# -- the model -------------------------------------------------------------------------------------------------------


def build_model(ckpt: Checkpoint):
    """The checkpoint's ``torch.nn.Module`` with its weights, in eval mode; CheckpointError if they do not fit.

    A zero input of the checkpoint's shape is run once, so a size mismatch fails here, not on the first frame.
    """
    import torch

    from brains.nets import make_model

    if ckpt.state_dict is None:
        raise CheckpointError(f"{ckpt.path}: has no weights for torch (an ONNX file serves with backend 'onnx' only)")
    try:
        model = make_model(ckpt.model, **ckpt.hyper)
        model.load_state_dict(ckpt.state_dict)
        model.eval()
        with torch.inference_mode():
            model(torch.zeros(input_shape(ckpt, batch=1)))
    except Exception as error:  # bad hyper (TypeError), wrong keys/shapes (RuntimeError), size mismatch at forward
        raise CheckpointError(f"{ckpt.path}: weights do not fit {ckpt.model} ({_first_line(error)})") from None
    return model


def input_shape(ckpt: Checkpoint, *, batch: int) -> tuple[int, ...]:
    """(batch, 3, H, W) for single-frame models, (batch, T, 3, H, W) for sequence models."""
    image = (3, ckpt.input.height_px, ckpt.input.width_px)
    return (batch, *image) if ckpt.frames == 1 else (batch, ckpt.frames, *image)


# -- ONNX metadata ---------------------------------------------------------------------------------------------------


def to_metadata(ckpt: Checkpoint) -> dict[str, str]:
    """What an exported ONNX file carries in ``metadata_props`` (string -> string; JSON for structures)."""
    spec = dataclasses.asdict(ckpt.input)
    return {
        "drivebench.format": ONNX_FORMAT,
        "drivebench.model": ckpt.model,
        "drivebench.hyper": json.dumps(ckpt.hyper),
        "drivebench.input": json.dumps(spec),
        "drivebench.normalisation": json.dumps(dataclasses.asdict(ckpt.normalisation)),
        "drivebench.source": str(ckpt.path),
    }


def from_metadata(meta: dict[str, str], path: str | Path) -> Checkpoint:
    """A weightless Checkpoint (state_dict None) described by an exported ONNX file's metadata."""
    path = Path(path)
    if meta.get("drivebench.format") != ONNX_FORMAT:
        raise CheckpointError(f"{path}: not exported by drivebench (no {ONNX_FORMAT} metadata)")
    try:
        raw = {
            "format": FORMAT,
            "model": meta["drivebench.model"],
            "hyper": json.loads(meta["drivebench.hyper"]),
            "state_dict": None,
            "input": json.loads(meta["drivebench.input"]),
            "normalisation": json.loads(meta["drivebench.normalisation"]),
            "dataset": {},
            "metrics": {},
            "training": {},
        }
    except (KeyError, json.JSONDecodeError) as error:
        raise CheckpointError(f"{path}: bad drivebench metadata ({_first_line(error)})") from None
    _check_keys(raw, path)
    return _parse(raw, path)


# -- packing (git-friendly form) -------------------------------------------------------------------------------------


def shard_names(dst: str | Path, count: int) -> list[Path]:
    """``dst.shard0`` ... ``dst.shard{count-1}``, beside ``dst``."""
    dst = Path(dst)
    return [dst.with_name(f"{dst.name}.shard{i}") for i in range(count)]


def pack_checkpoint(src: str | Path, dst: str | Path, *, half: bool = True, shard_bytes: int = 9 * 2**20) -> list[Path]:
    """Write checkpoint ``src`` in the packed form (module docstring) at ``dst``; returns the files written, shards
    first, ``dst`` last.

    half: floating tensors of the state dict as float16 (integer buffers such as BatchNorm's num_batches_tracked
    stay as they are); else float32. shard_bytes: the most bytes per shard file (at least one shard is written).
    Only :data:`PACKED_KEYS` are kept (no optimizer, rng or resume state). Every file is written under a temporary
    name and renamed, shards before ``dst``; shards left over from an earlier, larger pack at ``dst`` are removed.
    """
    import torch

    if shard_bytes < 1:
        raise ValueError(f"shard_bytes must be >= 1, got {shard_bytes}")
    src, dst = Path(src), Path(dst)
    raw = read_checkpoint(src)
    dtype = torch.float16 if half else torch.float32
    state = {
        k: v.detach().cpu().to(dtype) if v.is_floating_point() else v.detach().cpu()
        for k, v in raw["state_dict"].items()
    }
    buffer = io.BytesIO()
    torch.save(state, buffer)
    data = buffer.getvalue()
    blocks = [data[i : i + shard_bytes] for i in range(0, len(data), shard_bytes)] or [b""]
    shards = shard_names(dst, len(blocks))
    packed = {key: raw[key] for key in PACKED_KEYS if key in raw}
    packed["state_dict"] = {}
    packed[SHARDS_KEY] = {
        "files": [shard.name for shard in shards],
        "sha256": hashlib.sha256(data).hexdigest(),
        "file_sha256": [hashlib.sha256(block).hexdigest() for block in blocks],
        "dtype": "float16" if half else "float32",
        "bytes": len(data),
    }
    dst.parent.mkdir(parents=True, exist_ok=True)
    for shard, block in zip(shards, blocks):
        _write_atomically(shard, lambda file, block=block: file.write(block))
    _write_atomically(dst, lambda file: torch.save(packed, file))
    stale = len(shards)  # shards an earlier, larger pack left at dst
    while (old := dst.with_name(f"{dst.name}.shard{stale}")).is_file():
        old.unlink()
        stale += 1
    return [*shards, dst]


def _write_atomically(path: Path, write) -> None:
    temporary = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        with open(temporary, "wb") as file:
            write(file)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


# -- writing ---------------------------------------------------------------------------------------------------------


def write_checkpoint(raw: dict[str, Any], path: str | Path) -> Path:
    """Write a checkpoint dict (as :func:`read_checkpoint` returns it) with ``torch.save``, atomically and synced: a
    crash never leaves half a file (training writes its best and last checkpoints through it). Returns the path."""
    import torch

    path = Path(path)

    def write(file) -> None:
        torch.save(raw, file)
        file.flush()
        os.fsync(file.fileno())

    _write_atomically(path, write)
    return path


def save_checkpoint(
    path: str | Path,
    *,
    model_name: str,
    module,
    hyper: dict[str, Any] | None = None,
    input: dict[str, Any],
    normalisation: dict[str, Any],
    dataset: dict[str, Any] | None = None,
    metrics: dict[str, Any] | None = None,
    training: dict[str, Any] | None = None,
) -> Path:
    """Write ``module``'s weights as a ``drivebench.checkpoint.v1`` file (tests, benchmarks, smoke runs); returns the
    path."""
    return write_checkpoint(
        {
            "format": FORMAT,
            "model": model_name,
            "hyper": dict(hyper or {}),
            "state_dict": module.state_dict(),
            "input": input,
            "normalisation": normalisation,
            "dataset": dict(dataset or {}),
            "metrics": dict(metrics or {}),
            "training": dict(training or {}),
        },
        path,
    )


def default_input(
    model_name: str, *, offsets_frames: tuple[int, ...] = (-9, -5, 0), step_s: float = 0.05
) -> dict[str, Any]:
    """The paper's input for ``model_name`` (size, crop; frames t-9, t-5, t for sequence models) as a dict."""
    info = MODELS[model_name]
    frames = list(offsets_frames) if info.frames > 1 else [0]
    return {
        "width_px": info.input_width_px,
        "height_px": info.input_height_px,
        "crop_top_fraction": info.crop_top_fraction,
        "crop_bottom_fraction": 1.0,
        "offsets_frames": frames,
        "offsets_s": [round(o * step_s, 9) for o in frames],
        "step_s": step_s,
    }


def make_random_checkpoint(
    path: str | Path,
    model_name: str,
    *,
    seed: int = 0,
    label_mean: tuple[float, float] = (2.0, 0.0),
    label_std: tuple[float, float] = (0.5, 0.3),
    **input_options: Any,
) -> Path:
    """An untrained (seeded random init) checkpoint with made-up but valid normalisation, for tests and benchmarks.

    ``input_options`` go to :func:`default_input` (``offsets_frames``, ``step_s``). The weights are redrawn so that
    outputs are O(1) and depend on the image: the Keras init (zero biases, Glorot kernels, gated ConvLSTMs) leaves an
    untrained network's outputs near 1e-5, which would make parity and backend comparisons vacuous.
    """
    import torch

    from brains.nets import make_model

    generator = torch.Generator().manual_seed(seed)
    module = make_model(model_name)
    spec = default_input(model_name, **input_options)
    frames = len(spec["offsets_frames"])
    image = (3, spec["height_px"], spec["width_px"])
    _lively_init_(module, generator, (8, *image) if frames == 1 else (8, frames, *image))
    normalisation = {
        "image_mean": [0.485, 0.456, 0.406],
        "image_std": [0.229, 0.224, 0.225],
        "labels": "zscore",
        "label_mean": list(label_mean),
        "label_std": list(label_std),
    }
    return save_checkpoint(
        path,
        model_name=model_name,
        module=module,
        input=spec,
        normalisation=normalisation,
        training={"note": f"random init, seed {seed}"},
    )


def _lively_init_(module, generator, shape: tuple[int, ...]) -> None:
    """Random weights whose every layer matters: He-normal kernels, biases U(-0.2, 0.2) (BN untouched), then each
    conv/linear layer in turn rescaled so that its output has unit std on N(0, 1) inputs of ``shape`` (LSUV). The
    rescaling undoes the shrinking of stacked ConvLSTM gates, which would leave outputs almost input-independent."""
    import torch
    from torch import nn

    with torch.no_grad():
        for name, param in module.named_parameters():
            if param.dim() > 1:
                param.copy_(torch.randn(param.shape, generator=generator) * (2.0 / param[0].numel()) ** 0.5)
            elif "norm" not in name:
                param.copy_((torch.rand(param.shape, generator=generator) - 0.5) * 0.4)
        x = torch.randn(shape, generator=generator)
        module.eval()
        for layer in [m for m in module.modules() if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.Linear))]:
            seen: list = []
            hook = layer.register_forward_hook(lambda _m, _i, out: seen.append(out))
            module(x)
            hook.remove()
            if not seen:  # not called through forward (e.g. a ConvLSTM's recurrent conv on a zero state)
                continue
            scale = seen[0].std().clamp_min(1e-6)
            layer.weight.div_(scale)
            if layer.bias is not None:
                layer.bias.div_(scale)
