"""memDCCP (DeepestConvLSTMConv3DPilotnet): Conv3Ds over 3 frames, then four ConvLSTMs; 911 k parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
INFO = ModelInfo("memdccp", 50, 100, 3, 0.0, "brains.nets.memdccp.model:MemDCCP", 910_694)
