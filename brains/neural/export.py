"""ONNX export of a checkpoint (``drivebench export CKPT -o model.onnx``) and its parity check against PyTorch;
``drivebench pack CKPT -o model.ckpt`` writes the git-friendly packed form (float16 shards of at most 9 MiB,
:func:`brains.neural.checkpoint.pack_checkpoint`) and checks it against the original the same way.

The file has one input ``frames`` (float32 (B, 3, H, W), or (B, T, 3, H, W) oldest first; B is dynamic) and one
output ``command`` ((B, 2) normalised (v_n, w_n)). Its ``metadata_props`` carry the checkpoint's model, hyper,
input and normalisation as JSON (:func:`brains.neural.checkpoint.to_metadata`) and the checkpoint's sha256, so the
file serves on its own: ``python -m brains --brain memdccp --weights model.onnx`` needs onnxruntime, not torch.

Legacy TorchScript-based exporter (``dynamo=False``): all four networks export with it, and their outputs match
eager PyTorch within a few 1e-6.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

import numpy as np

from brains.neural.checkpoint import (
    Checkpoint,
    build_model,
    input_shape,
    load_checkpoint,
    to_metadata,
)
from brains.neural.runners import OrtRunner

INPUT_NAME, OUTPUT_NAME = "frames", "command"
SOURCE_SHA256_KEY = "drivebench.source_sha256"


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def export_onnx(
    ckpt_path: str | Path, out_path: str | Path, *, opset: int = 17, ckpt: Checkpoint | None = None
) -> Path:
    """Export checkpoint ``ckpt_path`` to ONNX at ``out_path`` (folders created); returns ``out_path``.

    ``ckpt``: the already loaded checkpoint of ``ckpt_path`` (saves loading it twice). The file is written under a
    temporary name and renamed, so a reader never sees half a file.
    """
    import onnx
    import torch

    ckpt = ckpt or load_checkpoint(ckpt_path)
    model = build_model(ckpt)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    partial = out_path.with_name(f".{out_path.name}.{os.getpid()}.partial")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation notices, once per export
            torch.onnx.export(
                model,
                (torch.zeros(input_shape(ckpt, batch=1)),),
                str(partial),
                dynamo=False,
                opset_version=opset,
                input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME],
                dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                do_constant_folding=True,
            )
        proto = onnx.load(str(partial))
        meta = {**to_metadata(ckpt), SOURCE_SHA256_KEY: file_sha256(ckpt.path)}
        onnx.helper.set_model_props(proto, meta)
        onnx.save(proto, str(partial))
        partial.replace(out_path)
    finally:
        partial.unlink(missing_ok=True)
    return out_path


def check_parity(ckpt_path: str | Path, onnx_path: str | Path, *, batch: int = 4, seed: int = 0) -> float:
    """Max |torch eager - onnxruntime| over the (batch, 2) normalised outputs for seeded N(0, 1) inputs (which is
    what ImageNet-normalised pixels look like)."""
    import torch

    ckpt = load_checkpoint(ckpt_path)
    model = build_model(ckpt)
    x = np.random.default_rng(seed).standard_normal(input_shape(ckpt, batch=batch)).astype(np.float32)
    with torch.inference_mode():
        expected = model(torch.from_numpy(x)).numpy()
    got = OrtRunner(onnx_path, threads=1)(x)
    return float(np.max(np.abs(expected - got)))


def pack_difference(original: str | Path, packed: str | Path, *, batch: int = 4, seed: int = 0) -> float:
    """Max |original - packed| over the (batch, 2) normalised outputs for seeded N(0, 1) inputs."""
    import torch

    ckpt_a, ckpt_b = load_checkpoint(original), load_checkpoint(packed)
    x = torch.from_numpy(
        np.random.default_rng(seed).standard_normal(input_shape(ckpt_a, batch=batch)).astype(np.float32)
    )
    with torch.inference_mode():
        return float((build_model(ckpt_a)(x) - build_model(ckpt_b)(x)).abs().max())
