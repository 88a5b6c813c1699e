"""The record of one ``DRIVEBENCH_*`` environment variable, and the circuit library's own: where user circuits live.

The one table of environment variables is :mod:`protocol.environment`; it lists :data:`CIRCUITS_DIR` from here. The
record type and this variable live on the ground floor so that the circuit library reads its folder without an
arrow back up to protocol/ (issue 41). Standard library only: importing it costs nothing.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Variable:
    """One environment variable.

    name: the variable (``DRIVEBENCH_...``).
    kind: what its value is, in words ("endpoints", "path", "pybullet, gl or auto", ...).
    default: what leaving it unset or empty means.
    meaning: what it sets.
    read_by: who reads it (processes, commands, compose, scripts).
    """

    name: str
    kind: str
    default: str
    meaning: str
    read_by: str

    def value(self) -> str:
        """The variable's value in this process's environment; "" when it is unset."""
        return os.environ.get(self.name, "")


CIRCUITS_DIR = Variable(
    name="DRIVEBENCH_CIRCUITS_DIR",
    kind="path to a folder",
    default="~/.local/share/drivebench/circuits",
    meaning="where user circuits live (`drivebench circuits import` writes there; every process loads from there)",
    read_by="every process that loads a circuit by name",
)
