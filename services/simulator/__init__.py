"""The simulator: a PyBullet world of one circuit, a kinematic car, a front camera; owns the episode clock."""
