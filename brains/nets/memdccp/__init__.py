"""memDCCP (DeepestConvLSTMConv3DPilotnet): Conv3Ds over 3 frames, then four ConvLSTMs; 911 k parameters."""
