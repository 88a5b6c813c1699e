"""Is a live view serving? Connect to a Foxglove WebSocket server as a viewer would and count camera images.

    .venv/bin/python scripts/foxglove_probe.py ws://127.0.0.1:8765 --seconds 8

Subscribes to the ground-truth camera (``/camera/truth``; ``.../sim/camera`` on servers from before stable topics),
decodes the JPEGs it receives until ``--seconds`` pass or the server goes away, and prints one JSON line: images,
rate, picture size. Exit 0 when at least one decodable image arrived, 1 otherwise. Needs ``websockets`` (the test
extra).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1
CAMERA_TOPICS = ("/camera/truth",)  # protocol.mapping.topics.CAMERA_TRUTH (this script imports nothing of the project)


def probe(url: str, *, seconds: float) -> dict:
    images, size = 0, None
    with connect(url, subprotocols=[SUBPROTOCOL], max_size=None, open_timeout=10) as ws:
        deadline = time.monotonic() + seconds
        first = None
        while (left := deadline - time.monotonic()) > 0:
            try:
                message = ws.recv(timeout=left)
            except (TimeoutError, ConnectionClosed):  # the server going away ends the count, it does not void it
                break
            if isinstance(message, str):
                body = json.loads(message)
                if body.get("op") == "advertise":
                    cameras = [
                        c for c in body["channels"] if c["topic"] in CAMERA_TOPICS or c["topic"].endswith("/sim/camera")
                    ]
                    if cameras:
                        ws.send(
                            json.dumps(
                                {
                                    "op": "subscribe",
                                    "subscriptions": [{"id": c["id"], "channelId": c["id"]} for c in cameras],
                                }
                            )
                        )
            elif message[0] == MESSAGE_DATA:
                image = CompressedImage()
                image.ParseFromString(message[13:])
                pixels = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
                if pixels is not None:
                    images += 1
                    size = f"{pixels.shape[1]}x{pixels.shape[0]}"
                    first = first or time.monotonic()
        span = time.monotonic() - first if first else 0.0
    return {
        "url": url,
        "images": images,
        "seconds": round(span, 2),
        "rate_hz": round((images - 1) / span, 1) if span > 0 else 0.0,
        "size": size,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("url", help="the server, e.g. ws://127.0.0.1:8765")
    parser.add_argument("--seconds", type=float, default=8.0, help="how long to listen (default 8)")
    args = parser.parse_args()
    try:
        result = probe(args.url, seconds=args.seconds)
    except OSError as error:
        print(f"foxglove_probe: cannot connect to {args.url}: {error}", file=sys.stderr)
        return 1
    print(json.dumps(result))
    return 0 if result["images"] else 1


if __name__ == "__main__":
    sys.exit(main())
