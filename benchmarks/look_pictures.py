"""The same camera pose in both looks, side by side, for simple, Montmelo (with the sun's shadows) and Montreal
(docs/look_side_by_side.png; both drawn by the gl renderer, whose flat look matches pybullet's).

.venv/bin/python benchmarks/look_pictures.py [-o docs/look_side_by_side.png] [--camera 320x240]
"""

from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np

from circuits import load_circuit
from protocol.episode_spec import CameraSpec, WorldVariation
from services.simulator.car import CarState
from services.simulator.renderers import make_scene

# (circuit, arc length m): poses where a wall's shadow falls on the road in the worlds that have shadows.
POSES = (("simple", 48.0), ("montmelo", 576.0), ("montreal", 358.0))


def label(tile: np.ndarray, text: str) -> np.ndarray:
    tile = cv2.cvtColor(tile, cv2.COLOR_RGB2BGR)
    for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(tile, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, colour, thickness, cv2.LINE_AA)
    return tile


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", default="docs/look_side_by_side.png")
    parser.add_argument("--camera", default="320x240", help="camera size WxH (default 320x240)")
    args = parser.parse_args()
    width, height = (int(value) for value in args.camera.split("x"))
    camera = CameraSpec(width_px=width, height_px=height)
    rows = []
    for name, s_m in POSES:
        circuit = load_circuit(name)
        car = CarState(*circuit.centreline.pose_at(s_m))
        tiles = []
        for look in ("flat", "gazebo"):
            with make_scene(circuit, WorldVariation(look=look), renderer="gl") as scene:
                tiles.append(label(scene.render(car, camera), f"{name} {s_m:g} m, look={look}"))
        rows.append(np.hstack(tiles))
    cv2.imwrite(args.output, np.vstack(rows))
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
