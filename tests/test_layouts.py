"""The shipped Foxglove layouts (docs/foxglove/): they parse, are what ``services.viz.layouts`` generates, hold the
panels the issue asks for, and name only topics (and fields, and frames) that recordings and the live view publish."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from support.recordings import one_run, write

from protocol import keys
from protocol.mapping import topics
from protocol.mapping.recording import channel_layout
from protocol.messages import LiveMetrics, Pose
from recorder.merge import merge
from recorder.reading import recording_info
from services.viz import layouts

FOLDER = Path(__file__).resolve().parents[1] / "docs" / "foxglove"
FIELDS_OF = {topics.CAR_STATE: Pose, topics.METRICS_LIVE: LiveMetrics}  # topics the plots read fields of


def load(name: str) -> dict[str, Any]:
    return json.loads((FOLDER / name).read_text())


def leaves(tree: Any) -> list[str]:
    if isinstance(tree, str):
        return [tree]
    assert set(tree) == {"direction", "first", "second", "splitPercentage"} and tree["direction"] in ("row", "column")
    return leaves(tree["first"]) + leaves(tree["second"])


def named_topics(layout: dict[str, Any]) -> dict[str, set[str]]:
    """Panel id -> every topic its config names (image topics, 3D topics, plot paths, table and log topics)."""
    named: dict[str, set[str]] = {}
    for panel_id, config in layout["configById"].items():
        found = set(config.get("topics", {}))
        found |= {config[k] for k in ("topicToRender",) if k in config}
        found |= {config["imageMode"]["imageTopic"]} if "imageMode" in config else set()
        found |= {re.split(r"[.{\[]", path["value"], maxsplit=1)[0] for path in config.get("paths", [])}
        found |= {re.split(r"[.{\[]", config["topicPath"], maxsplit=1)[0]} if "topicPath" in config else set()
        named[panel_id] = found
    return named


@pytest.mark.parametrize("name", [layouts.SINGLE, layouts.COMPARE])
def test_the_shipped_files_are_what_the_code_generates(name):
    assert (FOLDER / name).read_text() == layouts.render(layouts.layouts()[name]), (
        "regenerate with: python -m services.viz.layouts"
    )


@pytest.mark.parametrize("name", [layouts.SINGLE, layouts.COMPARE])
def test_the_layout_tree_and_panels_match(name):
    layout = load(name)
    assert set(layout) == {"configById", "globalVariables", "userNodes", "playbackConfig", "layout"}
    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    for panel_id, config in layout["configById"].items():
        assert re.fullmatch(r"(3D|Image|Plot|RosOut|Table)![a-zA-Z0-9-]+", panel_id)
        assert config["foxglovePanelTitle"] == config["lichtblickPanelTitle"] != ""


def test_the_single_run_layout_shows_what_the_issue_asks_for():
    layout = load(layouts.SINGLE)
    named = named_topics(layout)
    by_type: dict[str, list[set[str]]] = {}
    for panel_id, found in named.items():
        by_type.setdefault(panel_id.split("!")[0], []).append(found)
    assert {topics.CIRCUIT, topics.CAR_POSE} <= by_type["3D"][0]
    assert by_type["Image"] == [{topics.CAMERA_TRUTH}, {topics.CAMERA_BRAIN}]  # side by side
    assert layout["layout"]["first"]["second"] == {
        "direction": "row",
        "first": "Image!truth",
        "second": "Image!brain",
        "splitPercentage": 50,
    }
    plotted = {path["value"] for config in layout["configById"].values() for path in config.get("paths", [])}
    assert plotted == {
        "/car/state.speed_mps",
        "/car/state.yaw_rate_radps",
        "/metrics/live.cross_track_m",
        "/car/state.command_latency_ns",
    }
    assert by_type["RosOut"] == [{topics.EPISODE_LOG}] and by_type["Table"] == [{topics.EPISODE_SCORE}]
    assert layout["configById"]["3D!scene"]["followTf"] == "car"


def test_every_topic_field_and_frame_a_layout_names_is_published(tmp_path):
    """Against a real recording of one run and a real merge of two: what a viewer opening them would find."""
    one = write(tmp_path / "one.mcap", one_run("r1"), run_id="r1")
    two = write(tmp_path / "two.mcap", one_run("r2", brain="pilot"), run_id="r2")
    merged = merge([one, two], output=tmp_path / "merged.mcap").output
    for name, path in ((layouts.SINGLE, one), (layouts.COMPARE, merged)):
        layout = load(name)
        recorded = {c.topic for c in recording_info(path).channels}
        for panel_id, found in named_topics(layout).items():
            assert found, f"{name}: {panel_id} names no topic"
            assert found <= recorded, f"{name}: {panel_id} names topics nobody publishes: {found - recorded}"
        for config in layout["configById"].values():
            for path_ in config.get("paths", []):
                topic, _, field = path_["value"].partition(".")
                message_type = FIELDS_OF[re.sub(r"^/run[A-H]", "", topic)]
                schema = json.loads(channel_layout(keys.pose("r"), message_type).schema.data)
                assert field in schema["properties"], f"{name}: {path_['value']}: no field {field!r}"
        frames = {"world", "car"} if name == layouts.SINGLE else {"world", "runA/car", "runB/car"}
        assert layout["configById"]["3D!scene"]["followTf"] in frames
    # The single-run layout fits the live view too: its topics are a subset of what the bridge advertises.
    assert set().union(*named_topics(load(layouts.SINGLE)).values()) <= topics.run_topics()
