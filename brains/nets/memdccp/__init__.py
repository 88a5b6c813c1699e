"""memDCCP (DeepestConvLSTMConv3DPilotnet): Conv3Ds over 3 frames, then four ConvLSTMs; 911 k parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
INFO = ModelInfo(
    name="memdccp",
    input_height_px=50,
    input_width_px=100,
    frames=3,
    crop_top_fraction=0.0,
    module="brains.nets.memdccp.model:MemDCCP",
    reference_params=910_694,
)
