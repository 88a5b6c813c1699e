"""PilotNet x3: PilotNet convs per frame over 3 frames, then four 4-unit LSTMs; 353 k parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
INFO = ModelInfo("pilotnet_x3", 50, 100, 3, 0.0, "brains.nets.pilotnet_x3.model:PilotNetX3", 352_958)
