"""Training the networks: datasets to tensors, labels, augmentation, the training loop and its curve."""
