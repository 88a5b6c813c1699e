"""Is reading the dataset ever the training bottleneck? Loader samples/s against training samples/s, side by side.

Collects a small real dataset from the simulator (the explicit brain on ``simple``, 3-frame windows at 100x50, as
memDCCP and PilotNet x3 use), then measures in one run, interleaved:

* loader: ``DrivingDataset.batch`` of random indices (the gather training does), uint8;
* loader + to-tensor: the same batch turned into normalised float32 tensors (B, T, 3, H, W);
* a training step (forward, MSE, backward, Adam) of DeepestLSTMTinyPilotNet (the fastest network to train) and
  memDCCP, at the same batch size.

The ratio loader / training step says how many times faster the data arrives than the fastest network can use it.

    .venv/bin/python benchmarks/dataset.py [--batch 64] [--seconds 3] [--sim-seconds 30]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from recorder.dataset.build import DrivingDataset

ROOT = Path(__file__).resolve().parents[1]
MEAN = np.array([0.485, 0.456, 0.406], np.float32).reshape(1, 1, 3, 1, 1)
STD = np.array([0.229, 0.224, 0.225], np.float32).reshape(1, 1, 3, 1, 1)


def collect(folder: Path, sim_seconds: float) -> Path:
    out = folder / "data"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "orchestrator.cli",
            "dataset",
            "collect",
            "--circuits",
            "simple",
            "--max-sim-seconds",
            str(sim_seconds),
            "--history",
            "3",
            "--stride",
            "2",
            "--split",
            "none",
            "-o",
            str(out),
        ],
        check=True,
        cwd=ROOT,
    )
    return out


def rate(step, *, batch: int, seconds: float) -> float:
    """Samples per second of ``step()`` over about ``seconds`` (median of 5 slices)."""
    slices = []
    for _ in range(5):
        start, count = time.perf_counter(), 0
        while time.perf_counter() - start < seconds / 5:
            step()
            count += batch
        slices.append(count / (time.perf_counter() - start))
    return statistics.median(slices)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--sim-seconds", type=float, default=30.0)
    args = parser.parse_args()
    import torch

    from brains.nets import make_model

    with tempfile.TemporaryDirectory() as folder:
        dataset = DrivingDataset(collect(Path(folder), args.sim_seconds), split="train")
        rng = np.random.default_rng(0)

        def load():
            return dataset.batch(rng.integers(0, len(dataset), args.batch))

        def load_tensor():
            frames, labels = load()
            x = frames.transpose(0, 1, 4, 2, 3).astype(np.float32) / 255.0
            return torch.from_numpy((x - MEAN) / STD), torch.from_numpy(labels)

        rows = [
            ("loader (uint8 gather)", rate(load, batch=args.batch, seconds=args.seconds)),
            ("loader + normalised tensors", rate(load_tensor, batch=args.batch, seconds=args.seconds)),
        ]
        x, y = load_tensor()
        for name, inputs in (("deepest_lstm_tiny_pilotnet", x[:, -1]), ("memdccp", x)):
            model = make_model(name)
            optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)

            def train_step(model=model, optimiser=optimiser, inputs=inputs):
                optimiser.zero_grad()
                loss = torch.nn.functional.mse_loss(model(inputs), y)
                loss.backward()
                optimiser.step()

            rows.append((f"training step: {name}", rate(train_step, batch=args.batch, seconds=args.seconds)))
    fastest_training = max(r for name, r in rows if name.startswith("training"))
    print(f"\n{len(dataset)} samples of 3 x 100x50 frames, batch {args.batch}, {torch.get_num_threads()} threads\n")
    print("| stage | samples/s | x fastest training step |")
    print("|---|---|---|")
    for name, samples_per_s in rows:
        print(f"| {name} | {samples_per_s:,.0f} | {samples_per_s / fastest_training:.1f} |")


if __name__ == "__main__":
    main()
