"""Circuits: centreline geometry and the built-in circuit library (pure, no bus)."""

from services.circuits.centreline import Centreline, Projection
from services.circuits.library import Circuit, CircuitError, circuit_names, load_circuit

__all__ = ["Centreline", "Circuit", "CircuitError", "Projection", "circuit_names", "load_circuit"]
