"""PilotNet (Bojarski et al. 2016) as built by DeepLearningStudio: 66x200 input, 17.0 M parameters."""
