"""The protocol's MCAP mapping: every recorded message type back to the same message and the same wire bytes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support.messages import METRICS

from protocol import codec
from protocol.episode_spec import CameraSpec, EpisodeSpec, Gaussian, SaltPepper, WorldVariation
from protocol.mapping.recording import (
    RECORDED_MESSAGES,
    RecordFormatError,
    channel_layout,
    from_record,
    is_bus_channel,
    record_stamps,
    to_record,
)
from protocol.messages import (
    CameraFrame,
    Command,
    EndReason,
    EpisodeEvent,
    EpisodeScore,
    EventKind,
    Header,
    LiveMetrics,
    Pose,
)

HEADER = Header(run_id="r-1", episode=3, seq=41, stamp_ns=2_050_000_001)
SPEC = EpisodeSpec(
    circuit="montreal",
    seed=9,
    camera=CameraSpec(width_px=64, height_px=48, yaw_rad=0.1),
    world=WorldVariation(line="white", walls=False),
    noise=[SaltPepper(probability=0.1), Gaussian(sigma=3.5)],
)


def random_frame(*, dropped: bool = False) -> CameraFrame:
    pixels = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    return CameraFrame(
        header=HEADER, width_px=64, height_px=48, data=b"" if dropped else pixels.tobytes(), dropped=dropped
    )


MESSAGES = [
    random_frame(),
    random_frame(dropped=True),
    Pose(
        header=HEADER,
        x_m=1.25,
        y_m=-3.0000001,
        yaw_rad=3.1,
        speed_mps=4.5,
        yaw_rate_radps=-0.7,
        command_latency_ns=1_234_567,
    ),
    Command(header=HEADER, brain="explicit", frame_seq=41, speed_mps=3.0, yaw_rate_radps=0.1 + 0.2, inference_ns=999),
    EpisodeEvent(header=HEADER, kind=EventKind.START, spec=SPEC),
    EpisodeEvent(
        header=HEADER,
        kind=EventKind.END,
        reason=EndReason.OFF_TRACK,
        detail="left the road",
        last_pose_seq=40,
        wall_elapsed_ns=5,
    ),
    LiveMetrics(
        header=HEADER,
        progress_laps=0.5,
        laps_target=1,
        completed_laps=0,
        sim_time_s=2.05,
        real_time_factor=2.0,
        cross_track_m=-0.05,
        speed_mps=3.1,
    ),
    EpisodeScore(header=HEADER, spec=SPEC, reason=EndReason.TIME_LIMIT, brain="explicit", metrics=METRICS),
]


@pytest.mark.parametrize("message", MESSAGES, ids=lambda m: type(m).__name__)
def test_every_message_comes_back_with_its_wire_bytes(message):
    layout = channel_layout("drivebench/run/r-1/some/key", type(message))
    back = from_record(to_record(message), schema_name=layout.schema.name, metadata=layout.metadata)
    assert back == message
    assert codec.encode(back) == codec.encode(message)
    assert record_stamps(message) == (2_050_000_001, 41)


def test_every_recorded_type_is_covered():
    assert {type(m) for m in MESSAGES} == set(RECORDED_MESSAGES)


KEY = "drivebench/run/r1/k"  # channels are only made for run keys


def test_channels_are_viewable_without_plugins():
    for message_type in RECORDED_MESSAGES:
        layout = channel_layout(KEY, message_type)
        assert (layout.message_encoding, layout.schema.encoding) in {("protobuf", "protobuf"), ("json", "jsonschema")}
        assert is_bus_channel(layout.metadata)
    assert channel_layout(KEY, CameraFrame).schema.name == "foxglove.RawImage"
    assert channel_layout(KEY, CameraFrame, image_format="jpeg").schema.name == "foxglove.CompressedImage"


def test_json_schemas_name_the_fields_at_the_root():
    schema = json.loads(channel_layout(KEY, Command).schema.data)
    assert schema["type"] == "object"
    assert {"speed_mps", "yaw_rate_radps", "header"} <= set(schema["properties"])
    assert "$ref" not in json.dumps(schema)


def test_raw_images_read_by_foxglove_stock_schema():
    """A reader that knows only Foxglove's own RawImage still sees the picture (our fields are skipped)."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    frame = random_frame()
    image = RawImage()
    image.ParseFromString(to_record(frame))
    assert (image.width, image.height, image.encoding, image.step) == (64, 48, "rgb8", 64 * 3)
    assert image.data == frame.data
    assert image.timestamp.seconds == 2 and image.timestamp.nanos == 50_000_001


def test_jpeg_images_come_back_close_not_exact():
    frame = CameraFrame(
        header=HEADER, width_px=64, height_px=48, data=np.full((48, 64, 3), (200, 30, 30), np.uint8).tobytes()
    )
    layout = channel_layout(KEY, CameraFrame, image_format="jpeg")
    back = from_record(to_record(frame, image_format="jpeg"), schema_name=layout.schema.name, metadata=layout.metadata)
    assert (back.header, back.width_px, back.height_px) == (frame.header, 64, 48)
    error = np.abs(np.frombuffer(back.data, np.uint8).astype(int) - np.frombuffer(frame.data, np.uint8)).max()
    assert error <= 8


def test_bad_records_raise_one_clear_error():
    layout = channel_layout(KEY, Pose)
    with pytest.raises(RecordFormatError, match="Pose"):
        from_record(b'{"type": "drivebench.Pose.v1", "x_m": "far"}', schema_name="", metadata=layout.metadata)
    with pytest.raises(RecordFormatError, match="drivebench.type"):
        from_record(b"{}", schema_name="", metadata={"drivebench.key": "k"})
    camera = channel_layout(KEY, CameraFrame)
    with pytest.raises(RecordFormatError, match="RawImage"):
        from_record(b"\xff\xff\xff", schema_name=camera.schema.name, metadata=camera.metadata)
