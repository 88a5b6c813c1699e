"""Driven parity: the same brain drives one lap of the same circuit with each renderer; compare the scores.

Each episode is a plain ``drivebench run --json --renderer R`` (its own local stack, lock-step, seed 0), so the
numbers are the ones a user gets. Prints, per brain and circuit: how the episode ended, lap time, mean and RMS
cross-track error for pybullet and gl, and gl's difference from pybullet in per cent.

    .venv/bin/python benchmarks/renderer_laps.py [--brains explicit,deepest_lstm_tiny_pilotnet]
        [--circuits simple,many_curves,nurburgring,monaco] [--camera 320x240]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile

RENDERERS = ("pybullet", "gl")


def drive(*, brain: str, circuit: str, renderer: str, camera: str, runs_dir: str) -> dict:
    command = [
        sys.executable,
        "-m",
        "orchestrator.cli",
        "run",
        "--json",
        "--brain",
        brain,
        "--circuit",
        circuit,
        "--renderer",
        renderer,
        "--camera",
        camera,
        "--max-sim-seconds",
        "600",
        "--runs-dir",
        runs_dir,
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=3600)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed: {result.stderr.strip().splitlines()[-1:]}")
    return json.loads(result.stdout)


def per_cent(new: float, old: float) -> str:
    return f"{100 * (new - old) / old:+.1f} %" if old else "-"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--brains", default="explicit,deepest_lstm_tiny_pilotnet")
    parser.add_argument("--circuits", default="simple,many_curves,nurburgring,monaco")
    parser.add_argument("--camera", default="320x240")
    args = parser.parse_args()
    print("| brain | circuit | renderer | ended | lap time (s) | cross-track mean (m) | cross-track RMS (m) | RTF |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as runs_dir:
        for brain in args.brains.split(","):
            for circuit in args.circuits.split(","):
                scores = {
                    r: drive(brain=brain, circuit=circuit, renderer=r, camera=args.camera, runs_dir=runs_dir)
                    for r in RENDERERS
                }
                for renderer, score in scores.items():
                    metrics = score["metrics"]
                    lap = metrics["lap_times_s"][0] if metrics["lap_times_s"] else None
                    row = [
                        brain,
                        circuit,
                        renderer,
                        score["reason"],
                        f"{lap:.2f}" if lap else "-",
                        f"{metrics['cross_track_mean_m']:.4f}",
                        f"{metrics['cross_track_rms_m']:.4f}",
                        f"{metrics['real_time_factor']:.1f}x",
                    ]
                    if renderer == "gl":
                        base = scores["pybullet"]["metrics"]
                        base_lap = base["lap_times_s"][0] if base["lap_times_s"] else None
                        row[4] += f" ({per_cent(lap, base_lap)})" if lap and base_lap else ""
                        row[5] += f" ({per_cent(metrics['cross_track_mean_m'], base['cross_track_mean_m'])})"
                        row[6] += f" ({per_cent(metrics['cross_track_rms_m'], base['cross_track_rms_m'])})"
                    print("| " + " | ".join(row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
