"""The learning curve of a training run of examples/rl/train.py: progress and return per training episode against
environment steps, with the deterministic evaluations marked.

    python examples/rl/plot.py examples/rl/run -o docs/rl_learning_curve.png
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read_monitor(path: Path) -> list[dict]:
    """Stable-Baselines3's Monitor file: a JSON comment line, then r (return), l (length), t, progress_m, ..."""
    with open(path) as handle:
        next(handle)  # the "#{...}" header
        return list(csv.DictReader(handle))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="the --out folder of examples/rl/train.py")
    parser.add_argument("-o", "--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args()
    episodes = read_monitor(args.run / "monitor.csv")
    steps, total = [], 0
    for episode in episodes:
        total += int(episode["l"])
        steps.append(total)
    evaluations = list(csv.DictReader(open(args.run / "eval.csv"))) if (args.run / "eval.csv").is_file() else []
    figure, (progress_axis, return_axis) = plt.subplots(1, 2, figsize=(10, 3.6))
    progress_axis.plot(steps, [float(e["progress_m"]) for e in episodes], ".-", label="training episode")
    progress_axis.plot(
        [int(e["steps"]) for e in evaluations],
        [float(e["progress_m"]) for e in evaluations],
        "r*",
        markersize=12,
        label="deterministic evaluation",
    )
    progress_axis.axhline(440.0, color="grey", linestyle=":", label="one lap of simple (~440 m)")
    progress_axis.set(xlabel="environment steps", ylabel="progress along the centreline (m)")
    progress_axis.legend(fontsize=8)
    return_axis.plot(steps, [float(e["r"]) for e in episodes], ".-")
    return_axis.set(xlabel="environment steps", ylabel="episode return")
    figure.suptitle("SAC on drivebench/LaneFollow-v0 (simple, line features), seed 0: one training run")
    figure.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out, dpi=110)
    print(f"wrote {args.out}: {len(episodes)} training episodes, {total} steps, {len(evaluations)} evaluation(s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
