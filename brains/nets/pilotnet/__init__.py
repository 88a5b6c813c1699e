"""PilotNet (Bojarski et al. 2016) as built by DeepLearningStudio: 66x200 input, 17.0 M parameters."""

from brains.nets.info import ModelInfo

# What the network expects (torch-free: read by recorders and brains); its model is in model.py, loaded on demand.
INFO = ModelInfo(
    name="pilotnet",
    input_height_px=66,
    input_width_px=200,
    frames=1,
    crop_top_fraction=0.0,
    module="brains.nets.pilotnet.model:PilotNet",
    reference_params=17_016_206,
)
