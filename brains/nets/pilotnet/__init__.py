"""PilotNet (Bojarski et al. 2016) as built by DeepLearningStudio: 66x200 input, 17.0 M parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
INFO = ModelInfo("pilotnet", 66, 200, 1, 0.0, "brains.nets.pilotnet.model:PilotNet", 17_016_206)
