"""Matrices on Ray (``drivebench matrix FILE --ray ADDRESS``): their options, and the one-line how-to when Ray is not
installed. Light on purpose (``orchestrator.cli.ray`` reads them from the command line, for every ``drivebench``
command's parser); the engine itself (:mod:`orchestrator.matrix.ray_runner`) loads only when ``--ray`` is given."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from orchestrator.stack.launcher import StackError

RAY_MISSING = "--ray needs Ray: pip install 'drivebench[cluster]' (or: pip install 'ray>=2.50')"
EPISODE_SLOT = "episode_slot"  # the custom resource every worker node declares: episodes it runs at once
DEFAULT_NODE_RETRIES = 2


class ClusterError(StackError):
    """The matrix cannot run on this cluster (no Ray, no cluster at the address, no node with what it asks). One
    line."""


@dataclasses.dataclass(frozen=True)
class RayOptions:
    """Where and how a matrix runs on Ray.

    address: ``auto``, ``HOST:PORT`` (the head's GCS) or ``ray://HOST:10001`` (Ray Client).
    artifacts: a folder every node mounts; recordings go to ``<artifacts>/episodes/<index>/recording.mcap``.
    resources: what one episode asks for (``{"episode_slot": 1}`` plus any ``--ray-resource``).
    node_retries: how often an episode whose node (or worker process) died is submitted again.
    """

    address: str = "auto"
    artifacts: Path | None = None
    resources: dict = dataclasses.field(default_factory=lambda: {EPISODE_SLOT: 1.0})
    node_retries: int = DEFAULT_NODE_RETRIES


def import_ray():
    """The ``ray`` module, or :class:`ClusterError` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ClusterError(RAY_MISSING) from None
    return ray
