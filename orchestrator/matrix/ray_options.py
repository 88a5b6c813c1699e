"""Matrices on Ray (``drivebench matrix FILE --ray ADDRESS``): their options, the one-line how-to when Ray is not
installed, and the cluster (joining it, what its nodes offer). Light on purpose (Ray itself is imported only when a
function here is called; ``orchestrator.cli.ray`` reads the options for every ``drivebench`` command's parser); the
engine itself (:mod:`orchestrator.matrix.ray_runner`) loads only when ``--ray`` is given."""

from __future__ import annotations

import dataclasses
import logging
import socket
from pathlib import Path

from orchestrator.stack.failures import StackError

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


# -- the cluster --


def connect(address: str) -> None:
    """Join the cluster at ``address`` as a driver (nothing when this process already is one)."""
    ray = import_ray()
    if ray.is_initialized():
        return
    _probe(address)
    try:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    except ImportError as error:  # ray:// without Ray Client's packages
        raise ClusterError(f"{address!r} needs Ray Client: pip install 'ray[client]' ({error})") from None
    except (ConnectionError, RuntimeError, ValueError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ClusterError(f"no Ray cluster at {address!r}: {first}") from None


def _probe(address: str, *, timeout_s: float = 5.0) -> None:
    """A ``HOST:PORT`` where nothing listens, as one line at once (Ray itself would retry for minutes)."""
    if address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise ClusterError(f"--ray {address!r}: expected auto, HOST:PORT or ray://HOST:10001")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as error:
        raise ClusterError(
            f"no Ray cluster at {address!r}: nothing answers there ({error.strerror or error})"
        ) from None


def alive_nodes() -> list[dict]:
    return [node for node in import_ray().nodes() if node.get("Alive")]


def slots_of(node: dict, resources: dict) -> int:
    """How many episodes asking for ``resources`` fit on ``node`` at once."""
    offered = node.get("Resources", {})
    return int(min(offered.get(name, 0.0) / amount for name, amount in resources.items()) + 1e-9)


def capacity(resources: dict) -> int:
    """Episodes the cluster can run at once; :class:`ClusterError` (one line) when no node can run one."""
    nodes = alive_nodes()
    total = sum(slots_of(node, resources) for node in nodes)
    if total < 1:
        wanted = ", ".join(f"{name}={amount:g}" for name, amount in resources.items())
        offered = "; ".join(_offer(node) for node in nodes) or "no node alive"
        raise ClusterError(
            f"no node of the Ray cluster has what one episode asks for ({wanted}); the nodes offer: "
            f"{offered} (start workers with `ray start --address HEAD:6379 --resources "
            f"'{{\"{EPISODE_SLOT}\": N}}'`)"
        )
    return total


def _offer(node: dict) -> str:
    shown = {
        name: amount
        for name, amount in node.get("Resources", {}).items()
        if not name.startswith(("node:", "memory", "object_store_memory", "accelerator_type"))
    }
    return f"{node.get('NodeManagerAddress', '?')} " + (
        ", ".join(f"{name}={amount:g}" for name, amount in sorted(shown.items())) or "nothing"
    )


def task_resources(resources: dict) -> dict:
    """Ray task options for what one episode asks for: CPU and GPU are Ray's own fields (Ray refuses them among
    custom resources); the rest, episode_slot first, are custom resources. No CPU unless asked: the slot is the cap.
    A GPU share makes Ray set CUDA_VISIBLE_DEVICES for the task, which the stack's brain inherits."""
    custom = dict(resources)
    return {"num_cpus": custom.pop("CPU", 0), "num_gpus": custom.pop("GPU", 0), "resources": custom}


def node_label(*, ip: str, node_id: str) -> str:
    """How a results row names a Ray node: ``<ip>/<first 8 hex of its node id>`` (several nodes may share a host)."""
    return f"{ip}/{node_id[:8]}"
