"""Inference latency of the paper's four networks: eager PyTorch against onnxruntime, 1 and 2 threads, batch 1.

For each network (untrained weights: latency does not depend on their values) the four configurations (eager and
ORT, 1 and 2 intra-op threads) run in rotation, ``--block`` timed calls each after one untimed call (the thread
pool settles after a change of thread count), until each has ``--runs`` timings, so that machine load hits all of
them alike. Before timing, each configuration is warmed up with ``--warmup`` calls. Preprocessing (crop, INTER_AREA
resize, normalise, HWC -> CHW of a 320x240 frame, what the brain does once per frame) is timed in the same rotation.

Prints Markdown tables: median and p90 in ms, and ORT / eager (ratio of medians; below 1 = ORT faster).
Progress on stderr. Not a timed test; run it on a quiet machine and compare ratios, not absolute numbers.

    .venv/bin/python benchmarks/inference.py [--runs 200] [--warmup 30] [--block 10] [--models memdccp,...]
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

MODELS = ["pilotnet", "deepest_lstm_tiny_pilotnet", "pilotnet_x3", "memdccp"]
THREADS = (1, 2)


def percentile_ms(samples_s: list[float], q: float) -> float:
    return float(np.percentile(samples_s, q)) * 1e3


def configurations(name: str, folder: Path) -> tuple[dict[str, Callable[[], object]], dict[str, int]]:
    """name -> zero-argument call to time, and the torch thread count each call needs (0: none)."""
    import torch

    from brains.neural.brain import Preprocessor
    from brains.neural.checkpoint import build_model, input_shape, load_checkpoint, make_random_checkpoint
    from brains.neural.export import export_onnx
    from brains.neural.runners import OrtRunner

    ckpt = load_checkpoint(make_random_checkpoint(folder / f"{name}.pt", name))
    onnx_file = export_onnx(ckpt.path, folder / f"{name}.onnx", ckpt=ckpt)
    model = build_model(ckpt)
    x = np.random.default_rng(0).standard_normal(input_shape(ckpt, batch=1)).astype(np.float32)
    xt = torch.from_numpy(x)
    frame = np.random.default_rng(1).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    preprocess = Preprocessor(ckpt.input, ckpt.normalisation)

    def eager() -> object:
        with torch.inference_mode():
            return model(xt)

    calls: dict[str, Callable[[], object]] = {"preprocess": lambda: preprocess(frame)}
    torch_threads = {"preprocess": 0}
    for threads in THREADS:
        runner = OrtRunner(onnx_file, threads=threads)
        calls[f"eager{threads}"], torch_threads[f"eager{threads}"] = eager, threads
        calls[f"ort{threads}"], torch_threads[f"ort{threads}"] = functools.partial(runner, x), 0
    return calls, torch_threads


def measure(
    calls: dict[str, Callable[[], object]],
    torch_threads: dict[str, int],
    *,
    runs: int,
    warmup: int,
    block: int,
    bar: tqdm,
) -> dict[str, list[float]]:
    """Seconds per call of each configuration, ``runs`` each, taken in rotating blocks."""
    import torch

    def use(key: str) -> None:
        if torch_threads[key]:
            torch.set_num_threads(torch_threads[key])

    for key, call in calls.items():
        use(key)
        for _ in range(warmup):
            call()
    times: dict[str, list[float]] = {key: [] for key in calls}
    while any(len(t) < runs for t in times.values()):
        for key, call in calls.items():
            use(key)
            call()  # untimed: the first call after a thread-count change pays for it
            for _ in range(min(block, runs - len(times[key]))):
                started = time.perf_counter()
                call()
                times[key].append(time.perf_counter() - started)
                bar.update()
    return times


def tables(results: dict[str, dict[str, list[float]]], params: dict[str, int]) -> str:
    lines = [
        "| model | params | threads | eager median | eager p90 | ORT median | ORT p90 | ORT / eager |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, times in results.items():
        for threads in THREADS:
            eager, ort = times[f"eager{threads}"], times[f"ort{threads}"]
            lines.append(
                f"| {name} | {params[name]:,} | {threads} | {percentile_ms(eager, 50):.3f} | "
                f"{percentile_ms(eager, 90):.3f} | {percentile_ms(ort, 50):.3f} | "
                f"{percentile_ms(ort, 90):.3f} | {statistics.median(ort) / statistics.median(eager):.2f} |"
            )
    lines += ["", "| model | preprocessing 320x240 -> input: median | p90 |", "|---|---:|---:|"]
    lines += [
        f"| {name} | {percentile_ms(t['preprocess'], 50):.3f} | {percentile_ms(t['preprocess'], 90):.3f} |"
        for name, t in results.items()
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=200, help="timed calls per configuration (default 200)")
    parser.add_argument("--warmup", type=int, default=30, help="untimed calls per configuration first (default 30)")
    parser.add_argument("--block", type=int, default=10, help="timed calls per turn in the rotation (default 10)")
    parser.add_argument("--models", default=",".join(MODELS), help="comma-separated networks (default: all four)")
    args = parser.parse_args(argv)
    names = [n for n in args.models.split(",") if n]

    import onnxruntime
    import torch

    from brains.nets import MODELS as INFO

    results: dict[str, dict[str, list[float]]] = {}
    params: dict[str, int] = {}
    total = len(names) * (1 + 2 * len(THREADS)) * args.runs
    with (
        tempfile.TemporaryDirectory(prefix="drivebench-bench-") as folder,
        tqdm(total=total, desc="timed calls", file=sys.stderr, unit=" calls") as bar,
    ):
        for name in names:
            bar.set_postfix_str(name)
            calls, torch_threads = configurations(name, Path(folder))
            results[name] = measure(calls, torch_threads, runs=args.runs, warmup=args.warmup, block=args.block, bar=bar)
            params[name] = INFO[name].reference_params
    print(
        f"Batch 1, ms per call, {args.runs} runs after {args.warmup} warm-up, rotating blocks of {args.block}; "
        f"{os.cpu_count()} CPUs, torch {torch.__version__}, onnxruntime {onnxruntime.__version__}. "
        "Params: Keras count.\n"
    )
    print(tables(results, params))
    return 0


if __name__ == "__main__":
    sys.exit(main())
