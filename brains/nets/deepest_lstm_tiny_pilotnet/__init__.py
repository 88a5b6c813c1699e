"""DeepestLSTMTinyPilotNet: three valid convs + three single-step ConvLSTMs, cropped 50x100 input, 62 k parameters."""
