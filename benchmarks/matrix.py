"""Episodes per hour of a matrix, with 1 and with N workers, side by side in one run; and what a fresh stack per
episode costs against the episode itself.

    .venv/bin/python benchmarks/matrix.py [--episodes 6] [--sim-seconds 20] [--workers 2] [--renderers pybullet,gl]

Each renderer (``--renderers``) runs both cases, side by side in one run.

Every episode gets a fresh stack (its own processes under its own run id); the start-up share says what that
isolation costs. Lock-step episodes are CPU-bound, so more workers than cores buys nothing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from orchestrator.matrix import parse_matrix
from orchestrator.matrix_runner import MatrixRunner, RunOptions
from orchestrator.results import ResultStore


def matrix_text(*, episodes: int, sim_seconds: float, camera: str, renderer: str = "pybullet") -> str:
    return (f"name: bench\nbrains: [explicit]\ncircuits: [simple]\nrepetitions: {episodes}\n"
            f"limits: {{laps: 1, max_sim_seconds: {sim_seconds}}}\ncamera: {camera}\nrenderer: {renderer}\n")


def run_case(text: str, workers: int) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        started = time.monotonic()
        progress = MatrixRunner(parse_matrix(text), Path(folder), RunOptions(workers=workers)).run()
        wall_s = time.monotonic() - started
        with ResultStore(Path(folder), create=False) as store:
            results = store.results()
    episode_walls = [r.score.metrics.wall_time_s for r in results if r.score is not None]
    totals = [r.wall_s for r in results]
    return {"workers": workers, "done": progress.done, "failed": progress.failed, "wall_s": wall_s,
            "episodes_per_hour": 3600 * len(results) / wall_s,
            "episode_s": statistics.median(episode_walls), "overhead_s": statistics.median(
                [total - episode for total, episode in zip(totals, episode_walls)])}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--sim-seconds", type=float, default=20.0, help="simulated seconds per episode")
    parser.add_argument("--workers", type=int, default=2, help="the parallel case (the other is 1)")
    parser.add_argument("--camera", default="320x240")
    parser.add_argument("--renderers", default="pybullet,gl", help="renderers side by side (default pybullet,gl)")
    args = parser.parse_args()
    rows = []
    for renderer in args.renderers.split(","):
        text = matrix_text(episodes=args.episodes, sim_seconds=args.sim_seconds, camera=args.camera,
                           renderer=renderer)
        rows += [{**run_case(text, 1), "renderer": renderer}, {**run_case(text, args.workers), "renderer": renderer}]
    print(f"{args.episodes} episodes of at most {args.sim_seconds:.0f} s sim, one lap (explicit, simple, "
          f"{args.camera})\n")
    print("| renderer | workers | wall | episodes/hour | vs 1 worker | episode (sim loop) | stack start + stop per "
          "episode |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        base = next(r for r in rows if r["renderer"] == row["renderer"])["episodes_per_hour"]
        print(f"| {row['renderer']} | {row['workers']} | {row['wall_s']:.1f} s | {row['episodes_per_hour']:.0f} | "
              f"{row['episodes_per_hour'] / base:.2f}x | {row['episode_s']:.1f} s | {row['overhead_s']:.1f} s |")
    failed = sum(row["failed"] for row in rows)
    if failed:
        print(f"\n{failed} episode(s) failed", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
