"""The inference backends of a neural brain: float32 input of the checkpoint's input_shape -> (B, 2) normalised
outputs. Eager PyTorch (:class:`TorchRunner`, CPU or CUDA) and onnxruntime on CPU (:class:`OrtRunner`).

Their own module so that the brain and the ONNX export (whose parity check runs an :class:`OrtRunner`) both import
them without importing each other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brains.neural.checkpoint import Checkpoint, CheckpointError
from brains.registry import BrainOptionsError


class TorchRunner:
    """Eager PyTorch under ``inference_mode``; sets the process's torch thread count."""

    def __init__(self, ckpt: Checkpoint, *, threads: int, device: str = "cpu"):
        import torch

        from brains.neural.checkpoint import build_model

        torch.set_num_threads(threads)
        self._torch = torch
        self.device = torch_device(device)
        self.model = build_model(ckpt).to(self.device)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        with self._torch.inference_mode():
            return self.model(self._torch.from_numpy(x).to(self.device)).cpu().numpy()


def torch_device(name: str):
    """The torch device for the ``device`` option; a CUDA device this machine lacks is a one-line error."""
    import torch

    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise BrainOptionsError(f"device must be cpu, cuda, cuda:N or auto, got {name!r}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise BrainOptionsError(
                f"device {name!r}: no CUDA device here (torch {torch.__version__} sees none); use device=cpu or auto"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise BrainOptionsError(f"device {name!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif device.type != "cpu":
        raise BrainOptionsError(f"device must be cpu, cuda, cuda:N or auto, got {name!r}")
    return device


def ort_session(path: str | Path, *, threads: int = 1):
    """An onnxruntime CPU session: ``threads`` intra-op, 1 inter-op, sequential execution, all graph optimisations."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise BrainOptionsError(
            "backend 'onnx' needs onnxruntime (pip install onnxruntime, or the 'ml' extra); "
            "or use --set options.backend=torch"
        ) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3  # warnings about unused initialisers etc. are noise in the brain's log
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own Fail/InvalidProtobuf types
        raise CheckpointError(f"{path}: onnxruntime cannot load it ({str(error).splitlines()[0]})") from None


class OrtRunner:
    """onnxruntime on an ONNX file with one input (the frames) and one (B, 2) output."""

    def __init__(self, path: str | Path, *, threads: int):
        self.session = ort_session(path, threads=threads)
        self._input = self.session.get_inputs()[0].name
        self._output = self.session.get_outputs()[0].name

    def metadata(self) -> dict[str, str]:
        return dict(self.session.get_modelmeta().custom_metadata_map)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.session.run([self._output], {self._input: x})[0]
