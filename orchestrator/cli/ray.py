"""``--ray ADDRESS`` and its companions on ``drivebench matrix``, read into
``orchestrator.matrix.ray_options.RayOptions``."""

from __future__ import annotations

import argparse
from pathlib import Path

from orchestrator.matrix.ray_options import DEFAULT_NODE_RETRIES, EPISODE_SLOT, RayOptions


def add_ray_options(parser: argparse.ArgumentParser) -> None:
    """``--ray ADDRESS`` and its companions, on ``drivebench matrix``."""
    group = parser.add_argument_group("on a Ray cluster (pip install 'drivebench[cluster]')")
    group.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="run the episodes as tasks on the Ray cluster at ADDRESS: auto, HOST:PORT or "
        "ray://HOST:10001 (each worker node declares episode_slot resources)",
    )
    group.add_argument(
        "--artifacts",
        type=Path,
        metavar="DIR",
        help="with --ray: a folder every node mounts, for recordings (needed with --record)",
    )
    group.add_argument(
        "--ray-resource",
        action="append",
        default=[],
        metavar="NAME=AMOUNT",
        help="with --ray: what one episode asks for besides one episode_slot, e.g. GPU=0.25 (repeatable)",
    )
    group.add_argument(
        "--node-retries",
        type=int,
        default=DEFAULT_NODE_RETRIES,
        metavar="N",
        help=f"with --ray: how often an episode whose node died runs again elsewhere (default {DEFAULT_NODE_RETRIES})",
    )


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
        raise ValueError(
            "--record with --ray needs --artifacts DIR, a folder every node mounts (recordings are "
            "too large to travel through Ray)"
        )
    if args.workers != 1:
        raise ValueError(
            "--workers is for a local run: on Ray, the nodes' episode_slot resources set how many episodes run at once"
        )
    if args.node_retries < 0:
        raise ValueError(f"--node-retries must be >= 0, got {args.node_retries}")
    resources = {EPISODE_SLOT: 1.0, **parse_ray_resources(args.ray_resource, example="GPU=0.25")}
    artifacts = args.artifacts.resolve() if args.artifacts is not None else None
    return RayOptions(address=address.strip(), artifacts=artifacts, resources=resources, node_retries=args.node_retries)


def parse_ray_resources(items: list[str], *, example: str) -> dict[str, float]:
    """``--ray-resource NAME=AMOUNT`` items as a mapping; ValueError (one line, with ``example``) for a mistake."""
    resources: dict[str, float] = {}
    for item in items:
        name, _, amount = item.partition("=")
        try:
            value = float(amount)
        except ValueError:
            value = -1.0
        if not name.strip() or not value > 0:
            raise ValueError(f"--ray-resource {item!r}: expected NAME=AMOUNT with AMOUNT > 0, e.g. {example}")
        resources[name.strip()] = value
    return resources
