"""A lane-following policy trained by reinforcement learning (``examples/rl``), served as a brain.

``features`` turns a camera image into the small vector the policy reads (the same function the Gymnasium
environment uses for its ``observation="features"``), ``brain`` runs the exported policy on it.
"""
