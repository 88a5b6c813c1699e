"""DeepestLSTMTinyPilotNet: three valid convs + three single-step ConvLSTMs, cropped 50x100 input, 62 k parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
# The only one trained on the lower half of the 480-row frame (rows 240:480).
INFO = ModelInfo(
    name="deepest_lstm_tiny_pilotnet",
    input_height_px=50,
    input_width_px=100,
    frames=1,
    crop_top_fraction=0.5,
    module="brains.nets.deepest_lstm_tiny_pilotnet.model:DeepestLSTMTinyPilotNet",
    reference_params=62_470,
)
