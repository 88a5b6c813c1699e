"""Driving brains: the brain protocol, the registry, and the brain host process (``python -m brains``)."""

from brains.base import Action, Brain, Observation
from brains.registry import brain_names, make_brain, register

__all__ = ["Action", "Brain", "Observation", "brain_names", "make_brain", "register"]
