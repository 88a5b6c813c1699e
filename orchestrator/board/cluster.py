"""``drivebench board serve --ray ADDRESS``: the cluster is checked once, before the server starts, so that a
challenge never queues submissions it cannot evaluate: the cluster answers, a node has an episode slot, and, unless
``--unsafe-no-sandbox``, every node with a slot can sandbox a brain host (bubblewrap there; the episodes' brain hosts
are sandboxed on the node that runs them, by the same :class:`~orchestrator.matrix.runner.RunOptions` as here).

The evaluations themselves run through :class:`~orchestrator.matrix.ray_runner.RayMatrixRunner`
(:mod:`orchestrator.board.evaluate`); this server process leaves the cluster once checked.
"""

from __future__ import annotations

from orchestrator.matrix.ray_options import (
    ClusterError,
    RayOptions,
    alive_nodes,
    capacity,
    connect,
    import_ray,
    node_label,
    slots_of,
)

PROBE_TIMEOUT_S = 120.0  # a worker process per node to start, on a loaded machine


def check_cluster(address: str, *, sandboxed: bool) -> None:
    """:class:`ClusterError` (one line) unless the cluster at ``address`` can run a sandboxed episode."""
    connect(address)
    ray = import_ray()
    try:
        resources = dict(RayOptions().resources)
        capacity(resources)  # no node with an episode slot: one line naming what the nodes offer
        if sandboxed and (problems := _sandbox_problems(resources)):
            raise ClusterError(
                f"--ray {address}: cannot sandbox brains on every node ({'; '.join(problems)}): install bubblewrap "
                "there, or start with --unsafe-no-sandbox (trusted local use only)"
            )
    finally:
        ray.shutdown()


def _sandbox_problems(resources: dict) -> list[str]:
    """Per node that runs episodes, why it cannot sandbox a brain host (nothing when all can)."""
    ray = import_ray()
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    probe = ray.remote(num_cpus=0)(_sandbox_problem)
    nodes = [node for node in alive_nodes() if slots_of(node, resources) > 0]
    refs = [
        probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node_id=node["NodeID"], soft=False)).remote()
        for node in nodes
    ]
    answers = ray.get(refs, timeout=PROBE_TIMEOUT_S)
    return [
        f"{node_label(ip=node['NodeManagerAddress'], node_id=node['NodeID'])}: {problem}"
        for node, problem in zip(nodes, answers)
        if problem is not None
    ]


def _sandbox_problem() -> str | None:
    """On a node: why a brain host cannot be sandboxed here, or None."""
    from orchestrator.stack.sandbox import SandboxUnavailable, require_bubblewrap

    try:
        require_bubblewrap()
    except SandboxUnavailable as error:
        return str(error)
    return None
