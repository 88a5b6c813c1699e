"""Noise models: per-frame cost of each camera perturbation, against the identity and a plain frame copy.

Every model of ``services.noise.models`` with typical parameters (salt and pepper 0.2, gaussian sigma 10, blur 5,
brightness -0.3 / contrast 1.2, occlusion 2 x 0.2, JPEG 75, delay 3, drop 0.1), Behavior Metrics' perturbations
(rain, night, daytime, shadow, snow, fog, sunflare, affine; where albumentations is installed) and the identity (an
empty pipeline), at each camera size, on camera-like frames (colour gradients, edges, texture, mild sensor noise). All
cases are timed side by side in one run, interleaved in short blocks so that load changes on a shared machine hit
them alike; each figure is the median per-frame time over ``--frames`` frames after ``--warmup`` frames. Ratios are
to one copy (``np.copy``) of a 640x480 RGB frame, timed in the same blocks, so they compare across machines; the
milliseconds do not. Not a timed test.

    .venv/bin/python benchmarks/noise.py [--frames 200] [--warmup 20] [--sizes 640x480,200x66] [--threads N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import cv2
import numpy as np
from tqdm import tqdm

from protocol.episode_spec import (
    BM_NOISE_MODELS,
    Blur,
    Brightness,
    Delay,
    Drop,
    Gaussian,
    Jpeg,
    NoiseStage,
    Occlusion,
    SaltPepper,
)
from protocol.variations import noise_stage
from services.noise.models import MissingExtra, NoisePipeline, make_model, require_extras

DEFAULT_SIZES = "640x480,200x66"
BASELINE_SIZE = (640, 480)
BLOCK_FRAMES = 10  # frames per case per block; cases take turns block by block
FRAME_VARIANTS = 4  # distinct input frames per size, fed in turn

CASES: list[tuple[str, list[NoiseStage]]] = [
    ("identity (empty pipeline)", []),
    ("salt_pepper", [SaltPepper(probability=0.2)]),
    ("gaussian", [Gaussian(sigma=10.0)]),
    ("blur", [Blur(kernel_px=5)]),
    ("brightness", [Brightness(brightness=-0.3, contrast=1.2)]),
    ("occlusion", [Occlusion(patches=2, size_fraction=0.2)]),
    ("jpeg", [Jpeg(quality=75)]),
    ("delay", [Delay(frames=3)]),
    ("drop", [Drop(probability=0.1)]),
    # Behavior Metrics' perturbations (albumentations, BM's parameters): skipped without drivebench[bm]. Each made
    # from its name by noise_stage, which returns the NoiseStage that make_model takes.
    *((name, [noise_stage(name)]) for name in (str(model.__struct_config__.tag) for model in BM_NOISE_MODELS)),
]


def camera_like_frame(width: int, height: int, seed: int) -> np.ndarray:
    """Smooth colour gradients, a bright block with sharp edges, a textured band and mild noise; read-only."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    image = np.stack(
        [40 + 150 * x / width, 60 + 120 * y / height, 128 + 60 * np.sin(x / (width / 40) + y / (height / 25) + seed)],
        axis=2,
    )
    image[height // 3 : height // 2, width // 4 : width // 2] = (220, 30, 30)
    band = slice(2 * height // 3, 2 * height // 3 + max(1, height // 10))
    image[band] += rng.normal(0.0, 25.0, image[band].shape).astype(np.float32)
    image += rng.normal(0.0, 3.0, image.shape).astype(np.float32)
    frame = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    frame.flags.writeable = False  # as frames from the bus are
    return frame


def parse_sizes(text: str) -> list[tuple[int, int]]:
    sizes = []
    for item in text.split(","):
        width, height = (int(value) for value in item.strip().lower().split("x"))
        sizes.append((width, height))
    return sizes


def fmt(value: float) -> str:
    return f"{value:.3g}" if value >= 0.001 else f"{value:.1e}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200, help="timed frames per case and size")
    parser.add_argument("--warmup", type=int, default=20, help="untimed frames per case and size first")
    parser.add_argument("--sizes", default=DEFAULT_SIZES, help="camera sizes WxH, comma-separated")
    parser.add_argument("--threads", type=int, default=None, help="cv2.setNumThreads (default: OpenCV's own)")
    args = parser.parse_args()
    if args.threads is not None:
        cv2.setNumThreads(args.threads)
    sizes = parse_sizes(args.sizes)
    frames = {
        size: [camera_like_frame(*size, seed=seed) for seed in range(FRAME_VARIANTS)]
        for size in {*sizes, BASELINE_SIZE}
    }

    # (label, size) -> per-frame callable; the baseline copy is one more case
    runners: dict[tuple[str, tuple[int, int]], Callable[[np.ndarray], object]] = {("np.copy", BASELINE_SIZE): np.copy}
    for label, stages in CASES:
        try:
            require_extras(stages)
        except MissingExtra as missing:
            print(f"skipped {label}: {missing}", file=sys.stderr)
            continue
        for size in sizes:
            if stages:
                model = make_model(stages[0])
                model.reset(seed=0)
                runners[(label, size)] = model.apply
            else:
                pipeline = NoisePipeline([])
                pipeline.reset(seed=0)
                runners[(label, size)] = pipeline.apply
    timings: dict[tuple[str, tuple[int, int]], list[int]] = {key: [] for key in runners}

    for (_, size), run in runners.items():
        for index in range(args.warmup):
            run(frames[size][index % FRAME_VARIANTS])
    blocks = -(-args.frames // BLOCK_FRAMES)
    counter = 0
    for _ in tqdm(range(blocks), desc="noise benchmark", unit="block", file=sys.stderr):
        for key, run in runners.items():
            samples = timings[key]
            variants = frames[key[1]]
            for _ in range(BLOCK_FRAMES):
                frame = variants[counter % FRAME_VARIANTS]
                counter += 1
                started = time.perf_counter_ns()
                run(frame)
                samples.append(time.perf_counter_ns() - started)

    median_ms = {key: statistics.median(samples[: args.frames]) / 1e6 for key, samples in timings.items()}
    copy_ms = median_ms[("np.copy", BASELINE_SIZE)]
    print(
        f"Noise models, median ms per frame over {args.frames} frames (after {args.warmup} warm-up); "
        f"x copy = multiples of one {BASELINE_SIZE[0]}x{BASELINE_SIZE[1]} RGB frame copy ({fmt(copy_ms)} ms here). "
        f"NumPy {np.__version__}, OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)."
    )
    print()
    header = "| model | parameters |" + "".join(f" {w}x{h} ms | x copy |" for w, h in sizes)
    print(header)
    print("|---|---|" + "---:|---:|" * len(sizes))
    for label, stages in CASES:
        if (label, sizes[0]) not in median_ms:
            continue  # skipped: its extra is not installed
        fields = stages[0].__struct_fields__ if stages else ()
        params = ", ".join(f"{name}={getattr(stages[0], name)}" for name in fields)
        params = params or ("Behavior Metrics'" if stages else "")
        cells = "".join(
            f" {fmt(median_ms[(label, size)])} | {fmt(median_ms[(label, size)] / copy_ms)} |" for size in sizes
        )
        print(f"| {label} | {params} |{cells}")
    print(
        f"| np.copy (baseline) | {BASELINE_SIZE[0]}x{BASELINE_SIZE[1]} only |"
        + "".join(f" {fmt(copy_ms)} | 1 |" if size == BASELINE_SIZE else " - | - |" for size in sizes)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
