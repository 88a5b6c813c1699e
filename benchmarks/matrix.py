"""Episodes per hour of a matrix on fresh and on warm stacks, with 1 and with N workers, side by side in one run; and
what starting and stopping a stack costs against the episode itself.

    .venv/bin/python benchmarks/matrix.py [--episodes 6] [--sim-seconds 20] [--workers 2] [--renderers pybullet,gl]
    .venv/bin/python benchmarks/matrix.py --ray [--episodes 4] [--sim-seconds 60]

Each renderer (``--renderers``) runs four cases one after another: fresh stacks (``--fresh-stacks``: every episode
starts its own processes under its own run id) and warm stacks (each worker keeps its stack across episodes,
``orchestrator.matrix.executor``), each with 1 and with ``--workers`` workers. "rest per episode" is an episode's wall
time in the matrix less its simulation loop: for fresh stacks mostly starting and stopping the stack, for warm ones
the start request, the score's trip and writing the episode's files. Lock-step episodes are CPU-bound, so more
workers than cores buys nothing.

``--ray`` (needs ``drivebench[cluster]``) compares instead: 1 local worker, then a Ray cluster on this machine (a
head that runs no episode plus 1, then 2 worker nodes of one episode_slot each, every raylet on 127.0.0.1) running
the same matrix, and the time Ray adds per episode against the local worker, as a share of one episode: with fresh
stacks (a task per episode: dispatch, a worker process, the episode's own router, the result's trip) and with warm
ones (an episode slot actor per node, as a local warm worker). The local cases run with the idle cluster beside them,
so that both share the cores with Ray's own processes.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from orchestrator.matrix.load import parse_matrix
from orchestrator.matrix.results import ResultStore
from orchestrator.matrix.runner import MatrixRunner, RunOptions


def matrix_text(*, episodes: int, sim_seconds: float, camera: str, renderer: str = "pybullet") -> str:
    return (
        f"name: bench\nbrains: [explicit]\ncircuits: [simple]\nrepetitions: {episodes}\n"
        f"limits: {{laps: 1, max_sim_seconds: {sim_seconds}}}\ncamera: {camera}\nrenderer: {renderer}\n"
    )


def run_case(text: str, workers: int, *, fresh: bool = True, ray_address: str | None = None) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        started = time.monotonic()
        if ray_address is None:
            options = RunOptions(workers=workers, fresh_stacks=fresh)
            progress = MatrixRunner(parse_matrix(text), Path(folder), options).run()
        else:
            from orchestrator.matrix.ray_options import RayOptions
            from orchestrator.matrix.ray_runner import RayMatrixRunner

            options = RunOptions(fresh_stacks=fresh)
            ray_runner = RayMatrixRunner(
                parse_matrix(text), Path(folder), options, ray_options=RayOptions(address=ray_address)
            )
            progress = ray_runner.run()
        wall_s = time.monotonic() - started
        with ResultStore(Path(folder), create=False) as store:
            results = store.results()
    episode_walls = [r.score.metrics.wall_time_s for r in results if r.score is not None]
    totals = [r.wall_s for r in results]
    return {
        "workers": workers,
        "stacks": "fresh" if fresh else "warm",
        "stacks_started": len({r.run_id for r in results}),
        "done": progress.done,
        "failed": progress.failed,
        "wall_s": wall_s,
        "episodes_per_hour": 3600 * len(results) / wall_s,
        "task_s": statistics.median(totals),
        "episode_s": statistics.median(episode_walls),
        "overhead_s": statistics.median([total - episode for total, episode in zip(totals, episode_walls)]),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--sim-seconds", type=float, default=20.0, help="simulated seconds per episode")
    parser.add_argument("--workers", type=int, default=2, help="the parallel case (the other is 1)")
    parser.add_argument("--camera", default="320x240")
    parser.add_argument("--renderers", default="pybullet,gl", help="renderers side by side (default pybullet,gl)")
    parser.add_argument("--ray", action="store_true", help="1 local worker against a Ray cluster of 1 and 2 nodes")
    args = parser.parse_args()
    if args.ray:
        return ray_main(args, matrix_text(episodes=args.episodes, sim_seconds=args.sim_seconds, camera=args.camera))
    rows = []
    for renderer in args.renderers.split(","):
        text = matrix_text(episodes=args.episodes, sim_seconds=args.sim_seconds, camera=args.camera, renderer=renderer)
        for workers in sorted({1, args.workers}):  # --workers 1: one case each, not the same one twice
            for fresh in (True, False):
                rows.append({**run_case(text, workers, fresh=fresh), "renderer": renderer})
    print(
        f"{args.episodes} episodes of at most {args.sim_seconds:.0f} s sim, one lap (explicit, simple, {args.camera})\n"
    )
    print(
        "| renderer | workers | stacks | stacks started | wall | episodes/hour | warm vs fresh | vs 1 worker | "
        "episode (sim loop) | rest per episode |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        same = [r for r in rows if r["renderer"] == row["renderer"]]
        fresh_row = next(r for r in same if r["workers"] == row["workers"] and r["stacks"] == "fresh")
        one = next(r for r in same if r["workers"] == 1 and r["stacks"] == row["stacks"])
        print(
            f"| {row['renderer']} | {row['workers']} | {row['stacks']} | {row['stacks_started']} | "
            f"{row['wall_s']:.1f} s | {row['episodes_per_hour']:.0f} | "
            f"{row['episodes_per_hour'] / fresh_row['episodes_per_hour']:.2f}x | "
            f"{row['episodes_per_hour'] / one['episodes_per_hour']:.2f}x | {row['episode_s']:.1f} s | "
            f"{row['overhead_s']:.2f} s |"
        )
    failed = sum(row["failed"] for row in rows)
    if failed:
        print(f"\n{failed} episode(s) failed", file=sys.stderr)
    return 1 if failed else 0


def ray_main(args: argparse.Namespace, text: str) -> int:
    """Local 1 worker against Ray with 1 and with 2 worker nodes, and Ray's cost per episode."""
    import logging
    import os

    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # every Ray address on loopback (read at import)
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "node_ip_address": "127.0.0.1"})
    try:
        cluster.add_node(num_cpus=1, resources={"episode_slot": 1}, node_ip_address="127.0.0.1")
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, logging_level=logging.WARNING, log_to_driver=False)
        # The local runs with the idle cluster beside them: both cases then share the cores with Ray's own
        # processes, and the difference is what Ray's dispatch costs per episode.
        rows = []
        for fresh in (True, False):
            stacks = "fresh" if fresh else "warm"
            rows.append((f"local, 1 worker, {stacks}", run_case(text, 1, fresh=fresh)))
            rows.append((f"Ray, 1 worker node, {stacks}", run_case(text, 1, fresh=fresh, ray_address=cluster.address)))
        cluster.add_node(num_cpus=1, resources={"episode_slot": 1}, node_ip_address="127.0.0.1")
        cluster.wait_for_nodes()
        rows.append(("Ray, 2 worker nodes, warm", run_case(text, 2, fresh=False, ray_address=cluster.address)))
    finally:
        ray.shutdown()
        cluster.shutdown()
    print(
        f"{args.episodes} episodes of {args.sim_seconds:.0f} s sim (explicit, simple, {args.camera}); "
        f"{os.cpu_count()} cores\n"
    )
    print(
        "| runs on | stacks started | wall | episodes/hour | vs local | per episode (driver) | of which in the task |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, row in rows:
        base = rows[0][1] if row["stacks"] == "fresh" else rows[2][1]  # the local worker with the same stacks
        print(
            f"| {name} | {row['stacks_started']} | {row['wall_s']:.1f} s | {row['episodes_per_hour']:.0f} | "
            f"{row['episodes_per_hour'] / base['episodes_per_hour']:.2f}x | {row['wall_s'] / args.episodes:.1f} s | "
            f"{row['task_s']:.1f} s |"
        )
    for local, one_node in ((rows[0][1], rows[1][1]), (rows[2][1], rows[3][1])):
        added_s = (one_node["wall_s"] - local["wall_s"]) / args.episodes
        print(
            f"\nRay ({local['stacks']} stacks) adds {added_s:+.2f} s per episode against a local worker "
            f"({100 * added_s / (local['wall_s'] / args.episodes):+.1f} % of a {args.sim_seconds:.0f} s-sim episode)"
        )
    failed = sum(row["failed"] for _, row in rows)
    if failed:
        print(f"\n{failed} episode(s) failed", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
