"""Environment steps per second: drivebench/LaneFollow-v0 over the real stack, beside Gymnasium's CarRacing-v3
(Box2D, the anchor RL users know) and drivebench's in-process loop (the ceiling: the same rendering and physics in
one Python loop, no bus, no processes).

For each camera size, 1 env and 2 envs (``gymnasium.vector.AsyncVectorEnv``, each env its own stack) take random
actions for ``--steps`` steps each after a reset; only the stepping is timed (autoreset included: an episode that
ends starts the next on the same stack). CarRacing renders 96 x 96 only, so its 320 x 240 cells are empty. The
in-process loop is one env only. Configurations run one after the other under the same machine load; on a shared
machine only the ratios within one run mean anything, and on a saturated one wall-clock rates favour the
configurations with more processes (the scheduler shares the cores per thread, so a four-process stack gets more of
them than a one-process loop). So each cell also gives the CPU time per env step, summed over this process and every
process below it (the stacks, the vector env's workers; from /proc, Linux): the cost that does not depend on the
load.

    .venv/bin/python benchmarks/rl_env.py [--steps 300] [--sizes 96x96,320x240] [--renderer pybullet]

Not a timed test.
"""

from __future__ import annotations

import argparse
import functools
import os
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium.vector import AsyncVectorEnv

import drivebench  # noqa: F401 - registers the environment
from drivebench.rl.env import LaneFollowEnv
from protocol.episode_spec import CameraSpec, EpisodeSpec
from services.simulator.episode import EpisodeSim, SceneCache


def tree_cpu_s() -> float:
    """CPU seconds (user + system) of this process and every live process below it, from /proc."""
    parents, times = {}, {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as handle:
                fields = handle.read().rsplit(")", 1)[1].split()
        except OSError:
            continue  # gone meanwhile
        parents[int(entry)] = int(fields[1])
        times[int(entry)] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    ours, frontier = {os.getpid()}, [os.getpid()]
    while frontier:
        pid = frontier.pop()
        children = [child for child, parent in parents.items() if parent == pid and child not in ours]
        ours.update(children)
        frontier.extend(children)
    return sum(times.get(pid, 0.0) for pid in ours)


@dataclass(frozen=True)
class Rate:
    steps_per_s: float
    cpu_ms_per_step: float

    def __str__(self) -> str:
        return f"{self.steps_per_s:6.0f} ({self.cpu_ms_per_step:5.1f})"


def rate(env, *, steps: int, vector: bool, seed: int = 0) -> Rate:
    """Env steps per second and CPU ms per env step (a vector env of n counts n per step) over ``steps`` random
    steps after a reset."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    cpu_before, started = tree_cpu_s(), time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if not vector and (terminated or truncated):
            env.reset()
    elapsed, cpu_s = time.perf_counter() - started, tree_cpu_s() - cpu_before
    env_steps = steps * (env.num_envs if vector else 1)
    return Rate(env_steps / elapsed, 1e3 * cpu_s / env_steps)


def drivebench_env(*, width: int, height: int, renderer: str):
    # Random actions crash within seconds: the speed range keeps episodes going long enough to time steps.
    return functools.partial(
        LaneFollowEnv, camera=(width, height), renderer=renderer, speed_range_mps=(0.0, 3.0), live_metrics=False
    )


def measure_drivebench(*, width: int, height: int, renderer: str, envs: int, steps: int) -> Rate:
    make = drivebench_env(width=width, height=height, renderer=renderer)
    env = make() if envs == 1 else AsyncVectorEnv([make] * envs, context="spawn")
    try:
        return rate(env, steps=steps, vector=envs > 1)
    finally:
        env.close()


def measure_car_racing(*, envs: int, steps: int) -> Rate | None:
    try:
        make = functools.partial(gym.make, "CarRacing-v3")
        env = make() if envs == 1 else AsyncVectorEnv([make] * envs, context="spawn")
    except (gym.error.DependencyNotInstalled, ImportError):
        return None
    try:
        return rate(env, steps=steps, vector=envs > 1)
    finally:
        env.close()


def measure_in_process(*, width: int, height: int, renderer: str, steps: int) -> Rate:
    """EpisodeSim.render -> a random command -> EpisodeSim.step, in this process (what every env step does, less
    the bus, the processes, the scorer and the reward)."""
    spec = EpisodeSpec(camera=CameraSpec(width_px=width, height_px=height), renderer=renderer, max_sim_seconds=1e4)
    scenes = SceneCache()
    rng = np.random.default_rng(0)
    try:
        sim = EpisodeSim(spec, scenes=scenes)
        sim.render()
        cpu_before, started = time.process_time(), time.perf_counter()
        for _ in range(steps):
            sim.render()
            result = sim.step(speed_mps=float(rng.uniform(0, 3)), yaw_rate_radps=float(rng.uniform(-2, 2)))
            if result.end is not None:
                sim = EpisodeSim(spec, scenes=scenes)
        elapsed, cpu_s = time.perf_counter() - started, time.process_time() - cpu_before
        return Rate(steps / elapsed, 1e3 * cpu_s / steps)
    finally:
        scenes.close()


def cell(value: Rate | None) -> str:
    return "-" if value is None else str(value)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="timed steps per configuration (per env)")
    parser.add_argument("--sizes", default="96x96,320x240")
    parser.add_argument("--renderer", default="pybullet", choices=("pybullet", "gl"))
    args = parser.parse_args()
    sizes = [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")]
    names = ("drivebench 1", "drivebench 2", "CarRacing 1", "CarRacing 2", "in-process")
    print(f"env steps per second (CPU ms per env step), {args.steps} random steps per env, renderer {args.renderer}")
    print(f"{'camera':>9} " + " ".join(f"{name:>15}" for name in names) + f" {'CPU/step vs in-process':>23}")
    for width, height in sizes:
        kw = dict(width=width, height=height, renderer=args.renderer)
        one = measure_drivebench(**kw, envs=1, steps=args.steps)
        two = measure_drivebench(**kw, envs=2, steps=args.steps)
        native = (width, height) == (96, 96)
        racing = [measure_car_racing(envs=n, steps=args.steps) if native else None for n in (1, 2)]
        ceiling = measure_in_process(**kw, steps=args.steps)
        rates = (one, two, *racing, ceiling)
        ratio = one.cpu_ms_per_step / ceiling.cpu_ms_per_step
        size = f"{width}x{height}"
        print(f"{size:>9} " + " ".join(f"{cell(r):>15}" for r in rates) + f" {ratio:>22.1f}x", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
