"""RecurrentTinyPilotNet: DeepestLSTMTinyPilotNet's layers with memory that recurs over three frames (ours)."""
