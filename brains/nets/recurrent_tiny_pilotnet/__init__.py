"""RecurrentTinyPilotNet: DeepestLSTMTinyPilotNet's layers with memory that recurs over three frames (ours)."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
# Ours, not the paper's: the tiny network's layers with ConvLSTMs that recur over the three frames.
INFO = ModelInfo(
    "recurrent_tiny_pilotnet",
    50,
    100,
    3,
    0.0,
    "brains.nets.recurrent_tiny_pilotnet.model:RecurrentTinyPilotNet",
    62_470,
)
