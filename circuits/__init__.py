"""Circuits: centreline geometry and the built-in circuit library (pure, no bus)."""

from circuits.centreline import Centreline, Projection

# Importing the generator registers random:SEED, twisty:SEED and grandprix:SEED with the library (which must not
# import it).
from circuits.generator import grandprix_circuit, random_circuit, twisty_circuit
from circuits.library import Circuit, CircuitError, circuit_names, load_circuit

__all__ = [
    "Centreline",
    "Circuit",
    "CircuitError",
    "Projection",
    "grandprix_circuit",
    "circuit_names",
    "load_circuit",
    "random_circuit",
    "twisty_circuit",
]
