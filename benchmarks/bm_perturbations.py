"""Behavior Metrics' eight ``ImageTranform`` perturbations, measured: drivebench's against albumentations 1.0.3's.

BM pins albumentations 1.0.3; drivebench draws BM's perturbations itself (``services/noise/bm.py``) from what 1.0.3
was observed to do. This script renders real frames, applies each perturbation with one implementation, and prints
statistics a brain would notice: rain's streak length and count (on a black frame, where streaks are all there
is), the sky's and the road's HSV saturation and brightness, the fraction of pixels darkened or whitened, the black
strip of affine. Run it once per implementation and compare the two tables (docs/behavior-metrics.md has the
numbers). Not a test: the figures are means over ``--draws`` random draws.

    # 1. frames, with drivebench's venv
    .venv/bin/python benchmarks/bm_perturbations.py render -o /tmp/bm_frames.npz
    # 2. drivebench's perturbations
    .venv/bin/python benchmarks/bm_perturbations.py measure /tmp/bm_frames.npz --impl drivebench
    # 3. BM's: albumentations 1.0.3 in a throwaway venv (numpy, opencv and this file are all it needs)
    python3 -m venv /tmp/alb103
    /tmp/alb103/bin/pip install albumentations==1.0.3 'numpy<2' 'opencv-python-headless<4.9'
    /tmp/alb103/bin/python benchmarks/bm_perturbations.py measure /tmp/bm_frames.npz --impl albumentations

``--impl albumentations`` builds BM's transforms with the installed albumentations (1.0.3's keywords, or 2.x's).
"""

from __future__ import annotations

import argparse
import json
import random
import sys

import cv2
import numpy as np

NAMES = ("rain", "night", "daytime", "shadow", "snow", "fog", "sunflare", "affine")
SKY_ROWS = (0, 150)  # the camera's 640x480 frame: sky above the horizon (row ~240), road at the bottom
ROAD_ROWS = (360, 480)


def render(path: str) -> None:
    """Four frames of the simple circuit at 640x480 (BM's camera), default world."""
    from circuits import load_circuit
    from protocol.episode_spec import CameraSpec, WorldVariation
    from services.simulator.car import CarState
    from services.simulator.scene import Scene

    track = load_circuit("simple")
    camera = CameraSpec(width_px=640, height_px=480)
    with Scene.for_world(track, WorldVariation()) as scene:
        frames = [scene.render(CarState(*track.centreline.pose_at(s_m)), camera) for s_m in (10.0, 48.0, 120.0, 300.0)]
    np.savez_compressed(path, frames=np.stack(frames))
    print(f"wrote {path}", file=sys.stderr)


def albumentations_perturb(name: str):
    """BM's transform ``name`` (handler.transform_image), built with the installed albumentations."""
    import albumentations as A

    old = int(A.__version__.split(".")[0]) < 2
    always = {"always_apply": True} if old else {"p": 1.0}
    if name == "rain":
        slant = {"slant_lower": -10, "slant_upper": 10} if old else {"slant_range": (-10, 10)}
        keywords = dict(drop_length=20, drop_width=1, drop_color=(200, 200, 200), blur_value=7)
        transform = A.RandomRain(**slant, **keywords, brightness_coefficient=0.7, rain_type="torrential", **always)
    elif name in ("night", "daytime"):
        shift = -0.5 if name == "night" else 0.3
        transform = A.RandomBrightnessContrast(brightness_limit=(shift, shift), contrast_limit=(0, 0), **always)
    elif name == "affine":
        transform = A.Affine(translate_percent={"x": -0.1, "y": 0.0}, **always)
    else:
        kinds = {"shadow": A.RandomShadow, "snow": A.RandomSnow, "fog": A.RandomFog, "sunflare": A.RandomSunFlare}
        transform = kinds[name](**always)
    return lambda image, seed: transform(image=image)["image"]


def drivebench_perturb(name: str):
    from protocol.variations import noise_stage
    from services.noise.models import make_model

    model = make_model(noise_stage(name))

    def apply(image: np.ndarray, seed: int) -> np.ndarray:
        model.reset(seed=seed)
        out = model.apply(image)
        assert out is not None, "only drop and delay withhold a frame; BM's perturbations transform every one"
        return out

    return apply


def hsv_means(image: np.ndarray, rows: tuple[int, int]) -> tuple[float, float]:
    hsv = cv2.cvtColor(np.ascontiguousarray(image[rows[0] : rows[1]]), cv2.COLOR_RGB2HSV)
    return float(hsv[..., 1].mean()), float(hsv[..., 2].mean())


def streaks(image: np.ndarray) -> tuple[float, int, float]:
    """(median streak height px, streaks, ink) of rain drawn on a black frame: streaks are the thin connected
    components of pixels brighter than 10; ink is the frame's total grey level / 1000 (drops x length x colour)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    count, _, stats, _ = cv2.connectedComponentsWithStats((grey > 20).astype(np.uint8), connectivity=8)
    heights = [int(stats[i, cv2.CC_STAT_HEIGHT]) for i in range(1, count)]
    return (float(np.median(heights)) if heights else 0.0), count - 1, float(grey.sum()) / 1000


def measure(frames: np.ndarray, name: str, apply, *, draws: int) -> dict[str, float]:
    rows: list[dict[str, float]] = []
    for draw in range(draws):
        random.seed(draw)  # albumentations 1.0.3 draws from Python's random, 2.x from its own generator
        np.random.seed(draw)
        image = frames[draw % len(frames)]
        out = np.asarray(apply(image, draw))
        row: dict[str, float] = {}
        for region, span in (("sky", SKY_ROWS), ("road", ROAD_ROWS)):
            row[f"{region}_s"], row[f"{region}_v"] = hsv_means(out, span)
        diff = out.astype(int).sum(axis=2) - image.astype(int).sum(axis=2)
        row["darker_frac"] = float((diff < -30).mean())
        row["brighter_frac"] = float((diff > 30).mean())
        row["black_right_frac"] = float((out[:, -64:].max(axis=2) == 0).mean())
        if name == "rain":
            row["streak_px"], row["streaks"], row["ink_k"] = streaks(np.asarray(apply(np.zeros_like(image), draw)))
        rows.append(row)
    return {key: round(float(np.mean([row[key] for row in rows])), 3) for key in rows[0]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    render_parser = commands.add_parser("render", help="render the input frames (drivebench's venv)")
    render_parser.add_argument("-o", "--output", default="/tmp/bm_frames.npz")
    measure_parser = commands.add_parser("measure", help="statistics of each perturbation, one JSON line each")
    measure_parser.add_argument("frames")
    measure_parser.add_argument("--impl", choices=("drivebench", "albumentations"), required=True)
    measure_parser.add_argument("--draws", type=int, default=20)
    measure_parser.add_argument("--only", default=",".join(NAMES), help="comma-separated perturbations")
    args = parser.parse_args()
    if args.command == "render":
        render(args.output)
        return 0
    frames = np.load(args.frames)["frames"]
    original = {"sky_s": hsv_means(frames[0], SKY_ROWS)[0], "sky_v": hsv_means(frames[0], SKY_ROWS)[1]}
    print(json.dumps({"input frame 0": {key: round(value, 1) for key, value in original.items()}}))
    make = drivebench_perturb if args.impl == "drivebench" else albumentations_perturb
    for name in args.only.split(","):
        print(json.dumps({name: measure(frames, name, make(name), draws=args.draws)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
