"""PilotNet x3: PilotNet convs per frame over 3 frames, then four 4-unit LSTMs; 353 k parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
INFO = ModelInfo(
    name="pilotnet_x3",
    input_height_px=50,
    input_width_px=100,
    frames=3,
    crop_top_fraction=0.0,
    module="brains.nets.pilotnet_x3.model:PilotNetX3",
    reference_params=352_958,
)
