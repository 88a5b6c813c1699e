"""Stable topics, checked as a viewer would: a recording opened with the official MCAP reader holds the same topic set
and schemas in every run; files recorded before stable topics (run-id topics) still read back to the same bus
messages. The live view's test (``tests/test_viz.py``) asserts the same set over the WebSocket."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_validation import assert_valid_mcap
from support.recordings import LEGACY, expected_schemas, one_run, write

from protocol import codec, keys
from protocol.mapping import topics
from recorder.dataset.build import DatasetOptions, build_dataset
from recorder.reading import read_messages, recording_info

# -- the mapping -------------------------------------------------------------------------------------------------------


def test_every_recorded_key_has_a_stable_topic_without_the_run_id():
    for run in ("r1", "compose"):
        assert {
            topics.topic_of_key(k)
            for k in (
                keys.camera_raw(run),
                keys.camera_perturbed(run),
                keys.pose(run),
                keys.events(run),
                keys.live_metrics(run),
                keys.score(run),
                keys.command(run, "explicit"),
            )
        } == topics.run_topics(brains=("explicit",)) - set(topics.VIEW_TOPICS.values())
    assert topics.topic_of_key("drivebench/run/r1/future/thing") == "/future/thing"  # unknown: still run-free
    with pytest.raises(ValueError, match="not a run key"):
        topics.topic_of_key("drivebench/alive/r1")


def test_legacy_run_id_topics_map_to_the_stable_ones():
    assert topics.stable_topic("drivebench/run/abc/noise/camera") == "/camera/brain"
    assert topics.stable_topic("drivebench/run/abc/brain/pilot/cmd") == "/brain/pilot/cmd"
    assert topics.stable_topic("drivebench/run/abc/view/track") == "/circuit"
    assert topics.stable_topic("drivebench/run/abc/view/world_from_car") == "/tf"
    assert topics.stable_topic("/camera/truth") == "/camera/truth"
    with pytest.raises(ValueError, match="not a drivebench topic"):
        topics.stable_topic("camera")


# -- a recording, as a viewer opens it ---------------------------------------------------------------------------------


def official_channels(path: Path) -> tuple[dict[str, str], list, dict[str, dict[str, str]]]:
    """(topic -> schema name, the channels, file metadata by name), read with the official ``mcap`` reader."""
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        return schemas, list(summary.channels.values()), metadata


@pytest.mark.parametrize("image_format", ["raw", "jpeg"])
def test_two_runs_record_the_same_stable_topics_and_schemas(tmp_path, image_format):
    published = topics.run_topics(brains=("explicit",))
    seen = []
    for run in ("r1", "other-run"):
        path = write(tmp_path / f"{run}.mcap", one_run(run), run_id=run, image_format=image_format)
        schemas, channels, metadata = official_channels(path)
        assert schemas == expected_schemas(published, image=image_format)
        # The run id is in channel metadata and file metadata, never in a topic.
        assert all(channel.metadata[topics.RUN_ID_METADATA] == run for channel in channels)
        assert not any(run in topic for topic in schemas)
        assert metadata["drivebench.run"]["run_id"] == run and metadata["drivebench.recording"]["format"] == "2"
        keyed = {c.topic: c.metadata["drivebench.key"] for c in channels if "drivebench.key" in c.metadata}
        assert keyed[topics.CAMERA_TRUTH] == keys.camera_raw(run) and keyed["/brain/explicit/cmd"] == keys.command(
            run, "explicit"
        )
        assert_valid_mcap(path)
        seen.append(set(schemas))
    assert seen[0] == seen[1] == published  # one layout shows both


def test_a_viewer_decodes_each_stable_topic(tmp_path):
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    path = write(tmp_path / "a.mcap", one_run("r1"), run_id="r1")
    last: dict[str, bytes] = {}
    counts: dict[str, int] = {}
    with open(path, "rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            last[channel.topic] = message.data
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    image = RawImage.FromString(last[topics.CAMERA_TRUTH])  # Foxglove's stock schema: the extra fields are skipped
    assert (image.width, image.height, image.encoding) == (8, 6, "rgb8")
    assert PoseInFrame.FromString(last[topics.CAR_POSE]).pose.position.x == pytest.approx(2.4)
    transform = FrameTransform.FromString(last[topics.TF])
    assert (transform.parent_frame_id, transform.child_frame_id) == ("world", "car")
    assert [e.id for e in SceneUpdate.FromString(last[topics.CIRCUIT]).entities] == ["track", "car"]
    assert json.loads(last[topics.CAR_STATE])["speed_mps"] == 2.0  # plottable: /car/state.speed_mps
    assert json.loads(last[topics.METRICS_LIVE])["cross_track_m"] == 0.02
    assert json.loads(last[topics.EPISODE_SCORE])["header"]["run_id"] == "r1"  # the run id, in the message
    log_lines = [Log.FromString(last[topics.EPISODE_LOG])]
    assert counts[topics.EPISODE_LOG] == 3 and log_lines[-1].message == "episode 0: end reason laps_completed"


# -- old files ---------------------------------------------------------------------------------------------------------


def test_an_old_file_with_run_id_topics_reads_back_the_same_bus_messages_as_a_new_one(tmp_path):
    """The fixture was written by the recorder before stable topics; rewriting its messages with today's recorder
    changes every topic but not one bus key, message or log time that replay and datasets see."""
    old = list(read_messages(LEGACY))
    assert {r.key for r in old} == {
        keys.camera_raw("legacy1"),
        keys.camera_perturbed("legacy1"),
        keys.pose("legacy1"),
        keys.command("legacy1", "explicit"),
        keys.events("legacy1"),
        keys.live_metrics("legacy1"),
    }
    new_path = write(tmp_path / "new.mcap", [(r.key, r.message) for r in old], run_id="legacy1")
    new = list(read_messages(new_path))
    assert [(r.key, codec.encode(r.message), r.log_time_ns) for r in new] == [
        (r.key, codec.encode(r.message), r.log_time_ns) for r in old
    ]
    assert (
        {r.key for r in read_messages(LEGACY, keys_glob="*/sim/*")}
        == {r.key for r in read_messages(new_path, keys_glob="*/sim/*")}
        == {keys.camera_raw("legacy1"), keys.pose("legacy1"), keys.events("legacy1")}
    )

    old_info, new_info = recording_info(LEGACY), recording_info(new_path)
    assert all(c.topic.startswith("drivebench/run/legacy1/") for c in old_info.channels)
    assert {topics.stable_topic(c.topic) for c in old_info.channels} | {topics.EPISODE_LOG} == {
        c.topic for c in new_info.channels
    }  # the legacy mapping; the episode log is new
    assert sorted((c.key, c.run_id) for c in old_info.channels if c.bus_key) == sorted(
        (c.key, c.run_id) for c in new_info.channels if c.bus_key
    )

    datasets = []
    for name, path in (("old", LEGACY), ("new", new_path)):
        out = tmp_path / name
        build_dataset(
            [(name, lambda path=path: read_messages(path))],
            out_dir=out,
            progress=False,
            options=DatasetOptions(width_px=8, height_px=6, split="none"),
        )
        datasets.append({a: np.load(out / f"{a}.npy") for a in ("frames", "labels", "frame_seq")})
    assert len(datasets[0]["frames"]) == 2  # frames 0 and 1: the END event's stamp (50 ms) precedes frame 2
    for name in ("frames", "labels", "frame_seq"):
        assert np.array_equal(datasets[0][name], datasets[1][name])
