"""Renderer parity: the same poses drawn by PyBullet's TinyRenderer (the reference) and by the gl backend.

For every built-in circuit and every world variation (line red / white / none x road grey / white x walls on / off x
lighting sun / no_sun), plus the four camera presets on the default world, both renderers draw the same poses
(spread round the circuit, off the centre line and off the track heading: ``services.simulator.parity``). Prints,
per circuit and per variation: mean absolute difference (grey levels, 0..255), SSIM (mean and worst frame) and the
fraction of pixels that differ by more than 8 grey levels (worst frame). Not a test; ``tests/test_renderers.py``
holds a few poses to loose thresholds.

    .venv/bin/python benchmarks/renderer_parity.py [--poses 6] [--camera 320x240] [--circuits simple,montreal]
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any, NamedTuple

from circuits import load_circuit
from circuits.library import builtin_circuit_names
from protocol.episode_spec import CameraSpec, EpisodeSpec, WorldVariation
from protocol.variations import CAMERA_PRESETS, apply_variation
from services.simulator.gl_scene import GLScene
from services.simulator.parity import differing_fraction, mean_absolute_difference, parity_poses, ssim
from services.simulator.scene import Scene
from services.simulator.world import describe_world


class Pair(NamedTuple):
    """One pose drawn by both renderers, compared."""

    circuit: str
    variation: str  # the label of variations()
    mad: float  # mean absolute difference, grey levels
    ssim: float
    differing: float  # the fraction of pixels more than 8 grey levels apart


def variations() -> list[tuple[str, WorldVariation, dict[str, Any]]]:
    """(label, world, camera preset variation) for every world variation and every camera preset."""
    items: list[tuple[str, WorldVariation, dict[str, Any]]] = []
    for line, road, walls, lighting in itertools.product(
        ("red", "white", "none"), ("grey", "white"), (True, False), ("sun", "no_sun")
    ):
        label = f"line={line},road={road},walls={'on' if walls else 'off'},lighting={lighting}"
        items.append((label, WorldVariation(line=line, road=road, walls=walls, lighting=lighting), {}))
    for preset in CAMERA_PRESETS:
        items.append((f"camera={preset}", WorldVariation(), {"camera": preset}))
    return items


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=6, help="poses per circuit and variation (default 6)")
    parser.add_argument("--camera", default="320x240", help="camera size WxH (default 320x240)")
    parser.add_argument(
        "--circuits",
        default=",".join(builtin_circuit_names()),
        help="comma-separated circuits (default: every built-in)",
    )
    args = parser.parse_args()
    width, height = (int(v) for v in args.camera.lower().split("x"))
    rows: list[Pair] = []
    started = time.perf_counter()
    for circuit_name in args.circuits.split(","):
        circuit = load_circuit(circuit_name)
        poses = parity_poses(circuit, count=args.poses)
        for label, world, camera_variation in variations():
            spec = EpisodeSpec(camera=CameraSpec(width_px=width, height_px=height))
            if camera_variation:
                spec = apply_variation(spec, camera_variation)
            camera = spec.camera
            with Scene.for_world(circuit, world) as reference, GLScene(describe_world(circuit, world)) as fast:
                for pose in poses:
                    a, b = reference.render(pose, camera), fast.render(pose, camera)
                    rows.append(
                        Pair(circuit_name, label, mean_absolute_difference(a, b), ssim(a, b), differing_fraction(a, b))
                    )
        print(f"{circuit_name}: done ({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    print(
        f"renderer parity: PyBullet TinyRenderer vs gl (moderngl/EGL), {width}x{height}, {args.poses} poses per "
        f"circuit and variation, {len(rows)} frame pairs\n"
    )
    groupings: tuple[tuple[str, Callable[[Pair], str]], ...] = (
        ("per circuit (all variations)", lambda pair: pair.circuit),
        ("per variation (all circuits)", lambda pair: pair.variation),
    )
    for title, group_of in groupings:
        groups: defaultdict[str, list[Pair]] = defaultdict(list)
        for row in rows:
            groups[group_of(row)].append(row)
        print(f"| {title} | MAD mean | MAD max | SSIM mean | SSIM min | pixels > 8 levels, max |")
        print("|---|---|---|---|---|---|")
        for name, group in groups.items():
            mads, ssims, diffs = (
                [row.mad for row in group],
                [row.ssim for row in group],
                [row.differing for row in group],
            )
            print(
                f"| {name} | {statistics.mean(mads):.2f} | {max(mads):.2f} | {statistics.mean(ssims):.4f} | "
                f"{min(ssims):.4f} | {100 * max(diffs):.2f} % |"
            )
        print()
    mads, ssims, diffs = [row.mad for row in rows], [row.ssim for row in rows], [row.differing for row in rows]
    print(
        f"all: MAD mean {statistics.mean(mads):.2f}, max {max(mads):.2f}; SSIM mean {statistics.mean(ssims):.4f}, "
        f"min {min(ssims):.4f}; pixels > 8 levels max {100 * max(diffs):.2f} %"
    )
    worst = min(rows, key=lambda row: row.ssim)
    print(f"worst frame: {worst.circuit} {worst.variation}: MAD {worst.mad:.2f}, SSIM {worst.ssim:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
