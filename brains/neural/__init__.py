"""Serving the paper's trained networks as brains: checkpoints, the NeuralBrain, ONNX export.

Importing this package does not import torch (nor onnxruntime): checkpoints load torch when read, the brain's
backends load their runtime when built, so an exported ONNX file serves with onnxruntime alone.
"""

from brains.neural.checkpoint import Checkpoint, CheckpointError, InputSpec, Normalisation, load_checkpoint

__all__ = ["Checkpoint", "CheckpointError", "InputSpec", "Normalisation", "load_checkpoint"]
