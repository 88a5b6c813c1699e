"""Train a lane-following policy with Stable-Baselines3 SAC on drivebench/LaneFollow-v0 until it laps ``simple``.

    python examples/rl/train.py --out runs/rl            # the shipped policy: seed 0, stops at the first lap
    python examples/rl/train.py --steps 300 --out /tmp/s  # a smoke run (CI): a few hundred steps, no lap expected

Why this route: two shared CPU cores. The policy reads the 10 line features of ``brains.lane_policy.features``
(the red line's bearing at 1, 2, 3.5 and 6 m ahead, measured in the camera image, plus the previous action), as
Behavior Metrics' RL brains do, rather than pixels; SAC, off-policy, learns continuous steering from a few tens of
thousands of steps where PPO needs far more. Frames come from the gl renderer (10x faster than TinyRenderer here).

Every ``--eval-every`` steps the deterministic policy drives one episode on a second environment (its own stack);
training stops when that episode completes the lap. Written to ``--out``: ``monitor.csv`` (every training episode:
return, length, progress), ``eval.csv`` (every evaluation), ``sac.zip`` (the SB3 model), ``lane_policy.npz`` (the
exported policy the ``lane_policy`` brain serves) and ``training.json`` (settings, steps, minutes).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import gymnasium as gym

import drivebench  # noqa: F401 - registers drivebench/LaneFollow-v0

ENV_KWARGS = dict(
    circuit="simple",
    observation="features",
    camera=(320, 240),
    renderer="gl",
    speed_range_mps=(2.0, 8.0),
    yaw_rate_range_radps=(-2.0, 2.0),
    max_episode_s=150.0,
    live_metrics=False,
)


def make_env(monitor: Path | None = None):
    from stable_baselines3.common.monitor import Monitor

    env = gym.make("drivebench/LaneFollow-v0", **ENV_KWARGS)
    return Monitor(env, str(monitor) if monitor else None, info_keywords=("progress_m", "end_reason"))


def evaluate(model, env) -> dict:
    """One deterministic episode; its return, progress and end."""
    obs, _ = env.reset(seed=0)
    total, done, info = 0.0, False, {}
    while not done:
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, info = env.step(action)
        total += reward
        done = terminated or truncated
    return {"return": total, "progress_m": info["progress_m"], "end_reason": info["end_reason"]}


def build_callback(args, eval_env, rows: list):
    from stable_baselines3.common.callbacks import BaseCallback

    class LapStop(BaseCallback):
        """Evaluate every ``eval_every`` steps; stop when the deterministic policy laps."""

        def _on_step(self) -> bool:
            if self.num_timesteps % args.eval_every:
                return True
            result = {"steps": self.num_timesteps, "minutes": (time.time() - args.started) / 60}
            result |= evaluate(self.model, eval_env)
            rows.append(result)
            print(json.dumps(result), flush=True)
            self.model.save(args.out / f"sac_{self.num_timesteps}.zip")
            return result["end_reason"] != "laps_completed"

    return LapStop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200_000, help="training steps at most")
    parser.add_argument("--eval-every", type=int, default=5_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    import torch
    from stable_baselines3 import SAC

    from drivebench.rl.policy import export_sb3

    torch.set_num_threads(1)  # two shared cores: the stack's processes need the other one
    args.out.mkdir(parents=True, exist_ok=True)
    args.started = time.time()
    env, eval_env = make_env(args.out / "monitor.csv"), make_env()
    model = SAC(
        "MlpPolicy",
        env,
        policy_kwargs=dict(net_arch=[64, 64]),
        learning_starts=min(1_000, args.steps // 2),
        buffer_size=200_000,
        batch_size=128,
        seed=args.seed,
        verbose=0,
    )
    rows: list[dict] = []
    try:
        model.learn(total_timesteps=args.steps, callback=build_callback(args, eval_env, rows))
    finally:
        env.close()
        eval_env.close()
    model.save(args.out / "sac.zip")
    note = f"SAC seed {args.seed}, {model.num_timesteps} steps on simple (examples/rl/train.py)"
    export_sb3(
        model,
        args.out / "lane_policy.npz",
        speed_range_mps=ENV_KWARGS["speed_range_mps"],
        yaw_rate_range_radps=ENV_KWARGS["yaw_rate_range_radps"],
        note=note,
    )
    if rows:
        with open(args.out / "eval.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    summary = {
        "steps": model.num_timesteps,
        "minutes": (time.time() - args.started) / 60,
        "seed": args.seed,
        "env": ENV_KWARGS,
        "lapped": bool(rows and rows[-1]["end_reason"] == "laps_completed"),
    }
    (args.out / "training.json").write_text(json.dumps(summary, indent=2, default=list) + "\n")
    print(json.dumps(summary, default=list))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
