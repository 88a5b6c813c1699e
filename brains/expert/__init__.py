"""The privileged expert: drives from the car's ground-truth pose against the centre line, not from the camera."""
