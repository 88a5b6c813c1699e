"""Circuits: centreline geometry and the built-in circuit library (pure, no bus)."""

from circuits.centreline import Centreline, Projection
from circuits.library import Circuit, CircuitError, circuit_names, load_circuit

__all__ = ["Centreline", "Circuit", "CircuitError", "Projection", "circuit_names", "load_circuit"]
