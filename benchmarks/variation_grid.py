"""A grid of sample frames, one per world variation and camera preset, for the docs (docs/variations.png), in
either look (the gazebo look needs the gl renderer: docs/variations_gazebo.png).

.venv/bin/python benchmarks/variation_grid.py [-o docs/variations.png]
.venv/bin/python benchmarks/variation_grid.py --look gazebo -o docs/variations_gazebo.png
"""

from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np

from protocol.episode_spec import EpisodeSpec
from protocol.variations import apply_variation
from services.simulator.episode import EpisodeSim, SceneCache

VARIATIONS = [
    "line=red",
    "line=white",
    "line=none",
    "road=white",
    "walls=off",
    "lighting=no_sun",
    "camera=left",
    "camera=right",
    "camera=rotate_down",
    "camera=rotate_up",
    "camera_yaw_rad=0.2",
    "road=white,line=none,walls=off",
]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", default="docs/variations.png")
    parser.add_argument("--distance-m", type=float, default=48.0, help="where on the simple circuit (arc length)")
    parser.add_argument("--look", choices=("flat", "gazebo"), default="flat", help="the look (default flat)")
    args = parser.parse_args()
    renderer = "gl" if args.look == "gazebo" else "pybullet"
    scenes = SceneCache(capacity=2)
    tiles = []
    for text in VARIATIONS:
        spec = apply_variation(EpisodeSpec(circuit="simple", renderer=renderer), f"{text},look={args.look}")
        sim = EpisodeSim(spec, scenes=scenes)
        x, y, yaw = sim.circuit.centreline.pose_at(args.distance_m)
        sim.car = type(sim.car)(x_m=x, y_m=y, yaw_rad=yaw)
        tile = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2BGR)
        cv2.putText(tile, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(tile, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    scenes.close()
    rows = [np.hstack(tiles[i : i + 4]) for i in range(0, len(tiles), 4)]
    cv2.imwrite(args.output, np.vstack(rows))
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
