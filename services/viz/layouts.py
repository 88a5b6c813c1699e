"""The Foxglove layouts shipped in ``docs/foxglove/``, as code: ``python -m services.viz.layouts`` writes them.

They use only stable topics (``protocol.mapping.topics``), so one layout shows any recording and any live run with no
edit:

* ``drivebench-layout.json``: one run. The 3D panel (circuit and car, following the car), the ground-truth and
  perturbed cameras side by side, plots of speed, yaw rate, cross-track error and command latency, the episode log
  (Foxglove's Log panel) and the score (Table).
* ``drivebench-compare-layout.json``: two runs merged by ``drivebench recorder merge A.mcap B.mcap -o AB.mcap``
  (namespaces ``runA``, ``runB``): both cars on one circuit in the 3D panel, both brains' cameras side by side, each
  plot with one series per run, both logs and scores.

The format is the one Foxglove's "Import from file..." reads and "Export..." writes (``configById`` by panel id
``<type>!<id>``, a ``layout`` tree of row / column splits), which Lichtblick reads too.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from protocol.mapping import topics
from protocol.mapping.views import CAR_FRAME, WORLD_FRAME

LAYOUT_DIR = Path(__file__).resolve().parents[2] / "docs" / "foxglove"
SINGLE = "drivebench-layout.json"
COMPARE = "drivebench-compare-layout.json"

# (plot title, field of a topic): the signals a driving run is judged by.
PLOTS = (
    ("speed (m/s)", topics.CAR_STATE, "speed_mps"),
    ("yaw rate (rad/s)", topics.CAR_STATE, "yaw_rate_radps"),
    ("cross-track error (m)", topics.METRICS_LIVE, "cross_track_m"),
    ("command latency (ns)", topics.CAR_STATE, "command_latency_ns"),
)


def _split(direction: str, first: Any, second: Any, percent: float = 50) -> dict[str, Any]:
    return {"direction": direction, "first": first, "second": second, "splitPercentage": percent}


def _chain(direction: str, panels: list[Any]) -> Any:
    """Panels in equal parts along ``direction`` (a mosaic tree is binary)."""
    if len(panels) == 1:
        return panels[0]
    return _split(direction, panels[0], _chain(direction, panels[1:]), 100 / len(panels))


class _Builder:
    def __init__(self) -> None:
        self.config_by_id: dict[str, dict[str, Any]] = {}

    def panel(self, kind: str, name: str, title: str, config: dict[str, Any]) -> str:
        panel_id = f"{kind}!{name}"
        # Each app reads its own title key and ignores the other's.
        self.config_by_id[panel_id] = {**config, "foxglovePanelTitle": title, "lichtblickPanelTitle": title}
        return panel_id

    def three_d(self, name: str, *, namespaces: tuple[str, ...] | None, follow: str) -> str:
        shown: dict[str, dict[str, Any]] = {}
        for ns in namespaces or (None,):

            def topic(t: str, ns=ns) -> str:
                return t if ns is None else topics.namespaced(t, ns)

            shown[topic(topics.CIRCUIT)] = {"visible": True}
            shown[topic(topics.CAR_POSE)] = {"visible": True, "type": "arrow"}
        return self.panel(
            "3D",
            name,
            "car on the circuit",
            {
                "cameraState": {
                    "perspective": True,
                    "distance": 25,
                    "phi": 55,
                    "thetaOffset": 45,
                    "fovy": 45,
                    "near": 0.5,
                    "far": 5000,
                    "target": [0, 0, 0],
                    "targetOffset": [0, 0, 0],
                    "targetOrientation": [0, 0, 0, 1],
                },
                "followMode": "follow-position" if follow != WORLD_FRAME else "follow-none",
                "followTf": follow,
                "scene": {},
                "transforms": {},
                "topics": shown,
                "layers": {
                    "grid": {
                        "visible": True,
                        "layerId": "foxglove.Grid",
                        "frameId": WORLD_FRAME,
                        "size": 60,
                        "divisions": 60,
                        "lineWidth": 1,
                        "color": "#248eff40",
                        "position": [0, 0, 0],
                        "rotation": [0, 0, 0],
                    }
                },
            },
        )

    def image(self, name: str, title: str, topic: str) -> str:
        return self.panel("Image", name, title, {"imageMode": {"imageTopic": topic}})

    def plot(self, name: str, title: str, series: list[tuple[str, str]]) -> str:
        return self.panel(
            "Plot",
            name,
            title,
            {
                "paths": [
                    {"value": path, "label": label, "enabled": True, "timestampMethod": "receiveTime"}
                    for label, path in series
                ],
                "showLegend": True,
                "legendDisplay": "floating",
                "showXAxisLabels": True,
                "showYAxisLabels": True,
                "isSynced": True,
                "xAxisVal": "timestamp",
            },
        )

    def log(self, name: str, title: str, topic: str) -> str:
        return self.panel("RosOut", name, title, {"searchTerms": [], "minLogLevel": 1, "topicToRender": topic})

    def table(self, name: str, title: str, topic: str) -> str:
        return self.panel("Table", name, title, {"topicPath": topic})

    def layout(self, tree: Any) -> dict[str, Any]:
        return {
            "configById": self.config_by_id,
            "globalVariables": {},
            "userNodes": {},
            "playbackConfig": {"speed": 1.0},
            "layout": tree,
        }


def single_run_layout() -> dict[str, Any]:
    """The layout of one run (a recording or ``drivebench view``)."""
    b = _Builder()
    scene = b.three_d("scene", namespaces=None, follow=CAR_FRAME)
    cameras = _split(
        "row",
        b.image("truth", "camera: ground truth", topics.CAMERA_TRUTH),
        b.image("brain", "camera: what the brain sees (perturbed)", topics.CAMERA_BRAIN),
    )
    plots = [
        b.plot(f"plot{i}", title, [(title.split(" (")[0], f"{topic}.{field}")])
        for i, (title, topic, field) in enumerate(PLOTS)
    ]
    bottom = _split(
        "row",
        b.log("events", "episode events", topics.EPISODE_LOG),
        b.table("score", "score", topics.EPISODE_SCORE),
        55,
    )
    left = _split("column", scene, cameras, 60)
    right = _split("column", _chain("column", plots), bottom, 70)
    return b.layout(_split("row", left, right, 55))


def compare_layout(namespaces: tuple[str, ...] = topics.DEFAULT_NAMESPACES[:2]) -> dict[str, Any]:
    """The layout of runs merged by ``drivebench recorder merge`` (default namespaces ``runA``, ``runB``)."""
    b = _Builder()
    scene = b.three_d("scene", namespaces=namespaces, follow=WORLD_FRAME)
    cameras = _chain(
        "row",
        [
            b.image(f"brain-{ns}", f"{ns}: camera the brain sees", topics.namespaced(topics.CAMERA_BRAIN, ns))
            for ns in namespaces
        ],
    )
    plots = [
        b.plot(f"plot{i}", title, [(ns, f"{topics.namespaced(topic, ns)}.{field}") for ns in namespaces])
        for i, (title, topic, field) in enumerate(PLOTS)
    ]
    logs = _chain(
        "row",
        [
            b.log(f"events-{ns}", f"{ns}: episode events", topics.namespaced(topics.EPISODE_LOG, ns))
            for ns in namespaces
        ],
    )
    scores = _chain(
        "row",
        [b.table(f"score-{ns}", f"{ns}: score", topics.namespaced(topics.EPISODE_SCORE, ns)) for ns in namespaces],
    )
    left = _split("column", scene, cameras, 60)
    right = _split("column", _chain("column", plots), _split("column", logs, scores), 65)
    return b.layout(_split("row", left, right, 55))


def layouts() -> dict[str, dict[str, Any]]:
    """File name -> layout, for every shipped layout."""
    return {SINGLE: single_run_layout(), COMPARE: compare_layout()}


def render(layout: dict[str, Any]) -> str:
    return json.dumps(layout, indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write every shipped layout into ``docs/foxglove/`` (or the folder given)."""
    folder = Path(argv[0]) if argv else LAYOUT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    for name, layout in layouts().items():
        (folder / name).write_text(render(layout))
        print(folder / name)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
