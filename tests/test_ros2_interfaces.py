"""ROS 2's type hashes and CDR, computed by drivebench's own code (protocol.ros2) and checked against ROS 2's
published values and an independent implementation (rosbags)."""

from __future__ import annotations

import math

import pytest
from needs import require

from protocol.messages import CameraFrame, Command, Header, Pose
from protocol.ros2 import cdr, interfaces, messages

# RIHS01 values as ROS 2's generated interfaces carry them (ROS 2 Jazzy). Where each comes from:
# * std_msgs/msg/String: rmw_zenoh's docs/design.md, the `chatter` key of demo_nodes_cpp
#   (0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...).
# * geometry_msgs/msg/Twist, sensor_msgs/msg/Image, tf2_msgs/msg/TFMessage: the "Topic type hash" line that
#   `ros2 topic info -v` prints on a live ROS 2 graph (/cmd_vel, /camera/image_raw, /tf), quoted in public projects'
#   docs (found with the code search of this project's tools; ids 71450155719, 6303977444, 70676474423).
# * nav_msgs/msg/Odometry, rosgraph_msgs/msg/Clock, std_msgs/msg/Header, builtin_interfaces/msg/Time,
#   geometry_msgs/msg/Vector3: golden-hash tables of independent ROS 2 client libraries that check them against
#   rosidl's generated type descriptions (e.g. CHECK_GOLDEN_HASH(Odometry, ...), id 57484889911).
# rosbags' typestore (below) computes every one of them too, a second opinion independent of ours.
ROS2_HASHES = {
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "geometry_msgs/msg/Twist": "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "nav_msgs/msg/Odometry": "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "rosgraph_msgs/msg/Clock": "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564",
    "std_msgs/msg/Header": "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "builtin_interfaces/msg/Time": "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    "geometry_msgs/msg/Vector3": "RIHS01_cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d",
}


@pytest.mark.parametrize("type_name", sorted(ROS2_HASHES))
def test_type_hashes_computed_from_the_definitions_equal_ros2s(type_name):
    assert interfaces.type_hash(type_name) == ROS2_HASHES[type_name]


@pytest.fixture(scope="module")
def typestore():
    typesys = require("rosbags.typesys")
    return typesys.get_typestore(typesys.Stores.ROS2_JAZZY)


@pytest.mark.parametrize("type_name", interfaces.INTERFACES)
def test_every_type_hash_equals_rosbags(typestore, type_name):
    assert interfaces.type_hash(type_name) == typestore.hash_rihs01(type_name)


def test_dds_type_names_are_rmw_zenohs():
    assert interfaces.dds_type_name("geometry_msgs/msg/Twist") == "geometry_msgs::msg::dds_::Twist_"


def test_message_definitions_parse_in_rosbags_to_the_same_type(typestore):
    from rosbags.typesys import get_types_from_msg

    for type_name in interfaces.INTERFACES:
        text = interfaces.message_definition(type_name).split("=" * 80)[0]
        parsed = get_types_from_msg(text, type_name)[type_name]
        assert [name for name, _ in parsed[1]] == [field.name for field in interfaces.fields(type_name)]


def _samples():
    header = Header(run_id="r1", episode=0, seq=3, stamp_ns=150_000_000)
    pixels = bytes(range(256)) * 3  # 16x16 RGB: every byte value, so an offset shows
    frame = CameraFrame(header=header, width_px=16, height_px=16, data=pixels)
    pose = Pose(header=header, x_m=1.5, y_m=-2.25, yaw_rad=0.7, speed_mps=3.0, yaw_rate_radps=-0.4)
    command = Command(header=header, brain="explicit", frame_seq=3, speed_mps=2.5, yaw_rate_radps=0.125)
    stamp_ns = 1_234_567_891_011
    return {
        messages.IMAGE: messages.image(frame, stamp_ns=stamp_ns),
        messages.TWIST: messages.twist(command),
        messages.ODOMETRY: messages.odometry(pose, stamp_ns=stamp_ns),
        messages.TF_MESSAGE: messages.transforms(pose, stamp_ns=stamp_ns),
        messages.CLOCK: {"clock": messages.time(stamp_ns)},
        messages.STRING: {"data": '{"kind": "lap", "lap": 1} é'},
    }


def _plain(value):
    """A rosbags message (dataclasses, numpy arrays) as dicts, lists and bytes, for comparison with ours."""
    import numpy as np

    if isinstance(value, np.ndarray):
        return value.tobytes() if value.dtype == np.uint8 else value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {name: _plain(getattr(value, name)) for name in value.__dataclass_fields__ if name != "__msgtype__"}
    if isinstance(value, list):
        return [_plain(item) for item in value]
    return value


@pytest.mark.parametrize("type_name", sorted(_samples()))
def test_our_cdr_decodes_in_rosbags_and_rosbags_cdr_is_byte_for_byte_ours(typestore, type_name):
    value = _samples()[type_name]
    ours = cdr.encode(type_name, value)
    theirs = typestore.deserialize_cdr(ours, type_name)
    assert _plain(theirs) == value
    assert bytes(typestore.serialize_cdr(theirs, type_name)) == ours
    assert cdr.decode(type_name, bytes(typestore.serialize_cdr(theirs, type_name))) == value


def test_a_twist_from_rosbags_gives_the_speeds_a_car_takes(typestore):
    twist_type = typestore.types["geometry_msgs/msg/Twist"]
    vector_type = typestore.types["geometry_msgs/msg/Vector3"]
    twist = twist_type(linear=vector_type(x=1.25, y=9.0, z=9.0), angular=vector_type(x=9.0, y=9.0, z=-0.5))
    data = bytes(typestore.serialize_cdr(twist, "geometry_msgs/msg/Twist"))
    assert messages.speeds_of_twist(cdr.decode("geometry_msgs/msg/Twist", data)) == (1.25, -0.5)


def test_odometry_turns_yaw_into_a_unit_quaternion_about_z():
    pose = Pose(header=Header(run_id="r", episode=0, seq=0, stamp_ns=0), x_m=0.0, y_m=0.0, yaw_rad=math.pi / 2)
    orientation = messages.odometry(pose, stamp_ns=0)["pose"]["pose"]["orientation"]
    assert orientation == pytest.approx({"x": 0.0, "y": 0.0, "z": math.sqrt(0.5), "w": math.sqrt(0.5)})


@pytest.mark.parametrize(
    "data, message",
    [(b"\x00\x00\x00\x00" + bytes(48), "not little-endian plain CDR"), (b"\x00\x01\x00\x00" + bytes(20), "truncated")],
)
def test_bad_cdr_is_one_error_naming_the_type(data, message):
    with pytest.raises(cdr.CdrError, match=message):
        cdr.decode("geometry_msgs/msg/Twist", data)


# -- rmw_zenoh's names: the examples of ros2/rmw_zenoh docs/design.md, character for character ---------------------

DESIGN_STRING_HASH = ROS2_HASHES["std_msgs/msg/String"]


def test_topic_keys_are_the_design_documents():
    from protocol.ros2 import rmw_zenoh

    string = "std_msgs/msg/String"
    assert rmw_zenoh.topic_key(domain_id=0, topic="/chatter", type_name=string) == (
        f"0/chatter/std_msgs::msg::dds_::String_/{DESIGN_STRING_HASH}"
    )
    robot1 = rmw_zenoh.fully_qualified("chatter", namespace="/robot1")
    assert rmw_zenoh.topic_key(domain_id=0, topic=robot1, type_name=string) == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{DESIGN_STRING_HASH}"
    )
    assert rmw_zenoh.topic_key(domain_id=0, topic="/cmd_vel", type_name="geometry_msgs/msg/Twist") == (
        f"0/cmd_vel/geometry_msgs::msg::dds_::Twist_/{ROS2_HASHES['geometry_msgs/msg/Twist']}"
    )


def test_liveliness_tokens_are_the_design_documents():
    from protocol.ros2.rmw_zenoh import EntityKind, Node, qos_token

    listener = Node(domain_id=2, session_id="aac3178e146ba6f1fc6e6a4085e77f21", node_id=0, name="listener")
    assert listener.token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert listener.endpoint_token(
        entity_id=10, kind=EntityKind.SUBSCRIPTION, topic="chatter", type_name="std_msgs/msg/String"
    ) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{DESIGN_STRING_HASH}/::,10:,:,:,,"
    )
    talker = Node(domain_id=2, session_id="8b20917502ee955ac4476e0266340d5c", node_id=0, name="talker")
    assert talker.endpoint_token(
        entity_id=10,
        kind=EntityKind.PUBLISHER,
        topic="/chatter",
        type_name="std_msgs/msg/String",
        qos=qos_token(depth=7),
    ) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{DESIGN_STRING_HASH}/::,7:,:,:,,"
    )


def test_tokens_and_keys_are_valid_zenoh_key_expressions():
    import zenoh

    from protocol.ros2.rmw_zenoh import EntityKind, Node, topic_key

    node = Node(
        domain_id=0, session_id="0123456789abcdef0123456789abcdef", node_id=0, name="drivebench", namespace="/sim"
    )
    for key in (
        topic_key(domain_id=0, topic="/camera/truth/image_raw", type_name="sensor_msgs/msg/Image"),
        node.token(),
        node.endpoint_token(entity_id=1, kind=EntityKind.PUBLISHER, topic="odom", type_name="nav_msgs/msg/Odometry"),
    ):
        assert str(zenoh.KeyExpr(key)) == key
    assert "/%sim/drivebench/%sim%odom/" in node.endpoint_token(
        entity_id=1, kind=EntityKind.PUBLISHER, topic="odom", type_name="nav_msgs/msg/Odometry"
    )


def test_an_attachment_is_sequence_stamp_and_gid_little_endian():
    from protocol.ros2.rmw_zenoh import attachment, parse_attachment

    gid = bytes(range(16))
    data = attachment(sequence=258, source_timestamp_ns=1_700_000_000_000_000_001, gid=gid)
    assert data == (258).to_bytes(8, "little") + (1_700_000_000_000_000_001).to_bytes(8, "little") + b"\x10" + gid
    parsed = parse_attachment(data)
    assert (parsed.sequence, parsed.source_timestamp_ns, parsed.gid) == (258, 1_700_000_000_000_000_001, gid)
    with pytest.raises(ValueError, match="GID length"):
        parse_attachment(data[:-1])
