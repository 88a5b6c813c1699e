"""The command line of matrices on Ray (``drivebench matrix FILE --ray ADDRESS``): options, their checks, and the
one-line how-to when Ray is not installed. Light on purpose: every ``drivebench`` command builds its parser with
these, and the engine itself (:mod:`orchestrator.ray_matrix`) loads only when ``--ray`` is given."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from orchestrator.launcher import StackError

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


# -- the command line --

def add_ray_options(parser: argparse.ArgumentParser) -> None:
    """``--ray ADDRESS`` and its companions, on ``drivebench matrix``."""
    group = parser.add_argument_group("on a Ray cluster (pip install 'drivebench[cluster]')")
    group.add_argument("--ray", metavar="ADDRESS",
                       help="run the episodes as tasks on the Ray cluster at ADDRESS: auto, HOST:PORT or "
                            "ray://HOST:10001 (each worker node declares episode_slot resources)")
    group.add_argument("--artifacts", type=Path, metavar="DIR",
                       help="with --ray: a folder every node mounts, for recordings (needed with --record)")
    group.add_argument("--ray-resource", action="append", default=[], metavar="NAME=AMOUNT",
                       help="with --ray: what one episode asks for besides one episode_slot, e.g. GPU=0.25 "
                            "(repeatable)")
    group.add_argument("--node-retries", type=int, default=DEFAULT_NODE_RETRIES, metavar="N",
                       help=f"with --ray: how often an episode whose node died runs again elsewhere "
                            f"(default {DEFAULT_NODE_RETRIES})")


def ray_options_from(args: argparse.Namespace) -> RayOptions | None:
    """The Ray options of a parsed command line (None: run locally); ``ValueError`` (one line) for a mistake."""
    address = getattr(args, "ray", None)
    if address is None:
        if getattr(args, "artifacts", None) is not None or getattr(args, "ray_resource", None):
            raise ValueError("--artifacts and --ray-resource go with --ray ADDRESS")
        return None
    if not address.strip():
        raise ValueError("--ray needs an address: auto, HOST:PORT or ray://HOST:10001")
    if args.record and args.artifacts is None:
        raise ValueError("--record with --ray needs --artifacts DIR, a folder every node mounts (recordings are "
                         "too large to travel through Ray)")
    if args.workers != 1:
        raise ValueError("--workers is for a local run: on Ray, the nodes' episode_slot resources set how many "
                         "episodes run at once")
    if args.node_retries < 0:
        raise ValueError(f"--node-retries must be >= 0, got {args.node_retries}")
    resources = {EPISODE_SLOT: 1.0}
    for item in args.ray_resource:
        name, _, amount = item.partition("=")
        try:
            value = float(amount)
        except ValueError:
            value = -1.0
        if not name.strip() or value <= 0:
            raise ValueError(f"--ray-resource {item!r}: expected NAME=AMOUNT with AMOUNT > 0, e.g. GPU=0.25")
        resources[name.strip()] = value
    artifacts = args.artifacts.resolve() if args.artifacts is not None else None
    return RayOptions(address=address.strip(), artifacts=artifacts, resources=resources,
                      node_retries=args.node_retries)


def import_ray():
    """The ``ray`` module, or :class:`ClusterError` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ClusterError(RAY_MISSING) from None
    return ray
