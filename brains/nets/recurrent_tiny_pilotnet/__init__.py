"""RecurrentTinyPilotNet: DeepestLSTMTinyPilotNet's layers with memory that recurs over three frames (ours)."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
# Ours, not the paper's: the tiny network's layers with ConvLSTMs that recur over the three frames.
INFO = ModelInfo(
    name="recurrent_tiny_pilotnet",
    input_height_px=50,
    input_width_px=100,
    frames=3,
    crop_top_fraction=0.0,
    module="brains.nets.recurrent_tiny_pilotnet.model:RecurrentTinyPilotNet",
    reference_params=62_470,
)
