"""Contract tests over every bus message type, keys and config loading (pure: no bus)."""

from __future__ import annotations

import copy
import functools
import math
import operator

import msgpack
import msgspec
import pytest
from support.messages import METRICS

from protocol import codec, keys
from protocol.deploy.config import ConfigError, load_config
from protocol.episode_spec import Brightness, CameraSpec, Drop, EpisodeSpec, Gaussian, Occlusion, SaltPepper
from protocol.messages import (
    BUS_MESSAGES,
    BrainEvent,
    CameraFrame,
    Command,
    ControlReply,
    ControlRequest,
    EndReason,
    EpisodeEvent,
    EpisodeScore,
    EventKind,
    Header,
    LiveMetrics,
    Pose,
    ShadowDistance,
)

HEADER = Header(run_id="r1", episode=2, seq=7, stamp_ns=350_000_000)
SAMPLES = {
    CameraFrame: CameraFrame(header=HEADER, width_px=2, height_px=1, data=bytes(range(6))),
    Pose: Pose(
        header=HEADER, x_m=1.5, y_m=-2.0, yaw_rad=0.1, speed_mps=7.0, yaw_rate_radps=-0.2, command_latency_ns=1200
    ),
    Command: Command(
        header=HEADER, brain="explicit", frame_seq=7, speed_mps=8.0, yaw_rate_radps=0.3, inference_ns=1500
    ),
    EpisodeEvent: EpisodeEvent(header=HEADER, kind=EventKind.END, reason=EndReason.CRASH, last_pose_seq=7),
    BrainEvent: BrainEvent(header=HEADER, kind=EventKind.START, seed=7, realtime=True, perturbed=True),
    LiveMetrics: LiveMetrics(
        header=HEADER,
        progress_laps=0.5,
        laps_target=1,
        completed_laps=0,
        sim_time_s=3.0,
        real_time_factor=2.5,
        cross_track_m=0.1,
        speed_mps=7.0,
    ),
    EpisodeScore: EpisodeScore(
        header=HEADER, spec=EpisodeSpec(), reason=EndReason.TIME_LIMIT, brain="explicit", metrics=METRICS
    ),
    ControlRequest: ControlRequest(action="start", spec=EpisodeSpec(laps=2, camera=CameraSpec(width_px=64))),
    ControlReply: ControlReply(ok=True, detail="", episode=3, state="starting"),
}


def test_every_bus_message_has_a_sample():
    assert set(SAMPLES) == set(BUS_MESSAGES)


@pytest.mark.parametrize("message_type", BUS_MESSAGES, ids=lambda t: t.__name__)
def test_round_trip_is_exact(message_type):
    message = SAMPLES[message_type]
    assert codec.decode(codec.encode(message), message_type) == message


@pytest.mark.parametrize("message_type", BUS_MESSAGES, ids=lambda t: t.__name__)
def test_wire_format_is_plain_msgpack(message_type):
    """Any msgpack client reads our messages: a map with a versioned type tag and the fields by name."""
    as_seen_by_msgpack = msgpack.unpackb(codec.encode(SAMPLES[message_type]), raw=False)
    assert as_seen_by_msgpack["type"] == message_type.__struct_config__.tag
    assert as_seen_by_msgpack["type"].startswith("drivebench.") and as_seen_by_msgpack["type"].endswith(".v1")
    if "header" in as_seen_by_msgpack:
        assert as_seen_by_msgpack["header"] == {"run_id": "r1", "episode": 2, "seq": 7, "stamp_ns": 350_000_000}


def test_message_written_by_msgpack_decodes():
    payload = msgpack.packb(
        {
            "type": "drivebench.Command.v1",
            "brain": "mine",
            "frame_seq": 3,
            "speed_mps": 1.0,
            "yaw_rate_radps": 0.0,
            "header": {"run_id": "r", "episode": 0, "seq": 0, "stamp_ns": 150_000_000},
        }
    )
    command = codec.decode(payload, Command)
    assert command.brain == "mine" and command.frame_seq == 3 and command.inference_ns == 0


@pytest.mark.parametrize("message_type", BUS_MESSAGES, ids=lambda t: t.__name__)
def test_garbage_is_rejected_with_a_clear_error(message_type):
    for garbage in (b"", b"\xc1", b"not msgpack at all", msgpack.packb([1, 2, 3]), msgpack.packb({"type": "x"})):
        with pytest.raises(codec.DecodeError, match=f"not a valid {message_type.__name__}"):
            codec.decode(garbage, message_type)


def test_wrong_message_type_is_rejected_by_its_tag():
    with pytest.raises(codec.DecodeError, match=r"\$\.type"):
        codec.decode(codec.encode(SAMPLES[Pose]), Command)


def test_bad_field_names_its_path():
    raw = msgpack.unpackb(codec.encode(SAMPLES[Pose]))
    raw["header"]["seq"] = "seven"
    with pytest.raises(codec.DecodeError, match=r"\$\.header\.seq"):
        codec.decode(msgpack.packb(raw), Pose)


def test_invalid_values_are_rejected():
    raw = msgpack.unpackb(codec.encode(SAMPLES[ControlRequest]))
    raw["spec"]["laps"] = 0
    with pytest.raises(codec.DecodeError, match="laps must be >= 1"):
        codec.decode(msgpack.packb(raw), ControlRequest)


def test_a_start_before_the_start_line_is_refused_and_a_spec_without_a_start_decodes_to_the_line():
    with pytest.raises(ValueError, match=r"^start_m must be >= 0, got -1$"):
        EpisodeSpec(start_m=-1)
    raw = msgpack.unpackb(codec.encode(SAMPLES[ControlRequest]))
    raw["spec"]["start_m"] = -0.5
    with pytest.raises(codec.DecodeError, match="start_m must be >= 0, got -0.5"):
        codec.decode(msgpack.packb(raw), ControlRequest)
    del raw["spec"]["start_m"]  # as every spec recorded before the field existed
    assert codec.decode(msgpack.packb(raw), ControlRequest).spec.start_m == 0.0
    assert codec.decode(codec.encode(EpisodeSpec(start_m=120.5)), EpisodeSpec).start_m == 120.5


def test_keys_are_run_scoped_and_separate_ground_truth_from_perturbed():
    assert keys.camera_raw("a") != keys.camera_perturbed("a")
    assert keys.camera_raw("a").startswith(keys.run_prefix("a") + "/")
    assert keys.command("a", "explicit").startswith(keys.run_prefix("a") + "/")
    assert keys.brain_of_command_key(keys.command("a", "pilot-2")) == "pilot-2"
    assert keys.parse_alive(keys.alive("a", "brain", "explicit")) == ("a", "brain", "explicit")
    assert keys.run_prefix("a") != keys.run_prefix("b")


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "a b", "$x", "a?b", "x#"])
def test_key_chunks_reject_wildcards_and_separators(bad):
    with pytest.raises(ValueError, match="may only contain"):
        keys.run_prefix(bad)


class _Demo(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    run_id: str = "x"
    spec: EpisodeSpec = EpisodeSpec()


def test_config_file_and_overrides(tmp_path):
    path = tmp_path / "demo.yaml"
    path.write_text("run_id: fromfile\nspec:\n  laps: 3\n")
    config = load_config(_Demo, path=path, overrides=["spec.camera.width_px=64", "spec.seed=5"])
    assert config.run_id == "fromfile" and config.spec.laps == 3
    assert config.spec.camera.width_px == 64 and config.spec.seed == 5


def test_config_errors_name_file_and_field(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("spec:\n  laps: many\n")
    with pytest.raises(ConfigError, match=r"^\S*bad\.yaml:2: spec\.laps must be an integer, got 'many'$"):
        load_config(_Demo, path=path)
    with pytest.raises(
        ConfigError, match=r"^command line: unknown key 'colour' in the config \(allowed: run_id, spec\)$"
    ):
        load_config(_Demo, overrides=["colour=red"])
    with pytest.raises(ConfigError, match="key.path=value"):
        load_config(_Demo, overrides=["no-equals-sign"])
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(_Demo, path=tmp_path / "missing.yaml")
    path.write_text("- a list\n")
    with pytest.raises(ConfigError, match="mapping at the top level"):
        load_config(_Demo, path=path)


# -- non-finite values: one protocol-wide rule over every float field of every message type --------------------------

# The spec with every noise model that has a float field, so the floats inside the tagged union are reached too.
FULL_SPEC = EpisodeSpec(
    noise=[
        SaltPepper(probability=0.2),
        Gaussian(sigma=3.0),
        Brightness(brightness=0.1, contrast=1.2),
        Occlusion(size_fraction=0.3, probability=0.5),
        Drop(probability=0.1),
    ]
)
# Every message with each optional part filled in: every float field, however deep, carries a value.
FULL_SAMPLES = SAMPLES | {
    Command: msgspec.structs.replace(SAMPLES[Command], model_inference_ns=900, suddenness=0.1, gpu=True),
    EpisodeEvent: EpisodeEvent(header=HEADER, kind=EventKind.START, spec=FULL_SPEC),
    EpisodeScore: EpisodeScore(
        header=HEADER,
        spec=FULL_SPEC,
        reason=EndReason.LAPS_COMPLETED,
        brain="explicit",
        metrics=msgspec.structs.replace(
            METRICS,
            bm_lap_seconds=40.0,
            lap_times_s=[41.5],
            circuit_diameter_m=462.9,
            bm_mean_inference_time_s=0.004,
            bm_suddenness_distance=0.02,
        ),
        shadows=[
            ShadowDistance(
                brain="b",
                frames=3,
                speed_mae_mps=0.1,
                yaw_rate_mae_radps=0.2,
                yaw_rate_rmse_radps=0.3,
                yaw_rate_max_abs_radps=0.4,
            )
        ],
    ),
    ControlRequest: ControlRequest(action="start", spec=FULL_SPEC),
    ControlReply: ControlReply(ok=True, state="running", spec=FULL_SPEC),
}


def _holds_floats(info: msgspec.inspect.Type) -> bool:
    """A float, or an optional float or list of floats (the field itself holds the numbers)."""
    if isinstance(info, msgspec.inspect.UnionType):
        return any(_holds_floats(member) for member in info.types)
    if isinstance(info, msgspec.inspect.ListType):
        return _holds_floats(info.item_type)
    return isinstance(info, msgspec.inspect.FloatType)


def declared_floats(info: msgspec.inspect.Type) -> set[tuple[str, str]]:
    """(struct, field) of every float field reachable from a type, through structs, unions, lists and optionals."""
    if isinstance(info, msgspec.inspect.StructType):
        found = {(info.cls.__name__, field.name) for field in info.fields if _holds_floats(field.type)}
        return found.union(*(declared_floats(field.type) for field in info.fields))
    if isinstance(info, msgspec.inspect.UnionType):
        return set().union(*(declared_floats(member) for member in info.types))
    if isinstance(info, msgspec.inspect.ListType):
        return declared_floats(info.item_type)
    return set()


def float_values(info: msgspec.inspect.Type, raw, path: tuple = (), owner: tuple[str, str] = ("", "")):
    """(owner (struct, field), path in the wire map) of every float in ``raw``, a message as plain msgpack data."""
    if isinstance(raw, float):
        yield owner, path
    elif isinstance(info, msgspec.inspect.StructType) and isinstance(raw, dict):
        for field in info.fields:
            if field.encode_name in raw:
                at = path + (field.encode_name,)
                yield from float_values(field.type, raw[field.encode_name], at, (info.cls.__name__, field.name))
    elif isinstance(info, msgspec.inspect.UnionType):
        for member in info.types:
            if isinstance(member, msgspec.inspect.StructType) and isinstance(raw, dict):
                if member.tag is None or raw.get(member.tag_field) == member.tag:
                    yield from float_values(member, raw, path, owner)
            elif isinstance(member, msgspec.inspect.ListType):
                yield from float_values(member, raw, path, owner)
    elif isinstance(info, msgspec.inspect.ListType) and isinstance(raw, list):
        for index, item in enumerate(raw):
            yield from float_values(info.item_type, item, path + (index,), owner)


def path_text(path: tuple) -> str:
    """A wire path as msgspec writes it in errors: ``$.spec.noise[1].sigma``."""
    return "$" + "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in path)


@pytest.mark.parametrize("message_type", BUS_MESSAGES, ids=lambda t: t.__name__)
def test_the_full_samples_carry_every_float_field(message_type):
    raw = msgpack.unpackb(codec.encode(FULL_SAMPLES[message_type]))
    covered = {owner for owner, _ in float_values(msgspec.inspect.type_info(message_type), raw)}
    assert covered == declared_floats(msgspec.inspect.type_info(message_type))


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("message_type", BUS_MESSAGES, ids=lambda t: t.__name__)
def test_a_non_finite_value_in_any_float_field_is_rejected_naming_the_field(message_type, value):
    raw = msgpack.unpackb(codec.encode(FULL_SAMPLES[message_type]))
    for (_, field), path in float_values(msgspec.inspect.type_info(message_type), raw):
        bad = copy.deepcopy(raw)
        parent = functools.reduce(operator.getitem, path[:-1], bad)
        parent[path[-1]] = value
        with pytest.raises(codec.DecodeError) as error:
            codec.decode(msgpack.packb(bad), message_type)
        text = str(error.value)
        assert text.startswith(f"not a valid {message_type.__name__}: "), text
        # The field's path, or (a check in the struct's __post_init__, where msgspec gives the struct's path) its
        # name and the path of the struct that holds it.
        field_at = path[: max(i for i, part in enumerate(path) if part == field) + 1]
        assert path_text(field_at) in text or (field in text and f"`{path_text(field_at[:-1])}`" in text), text


# -- what brains are told of an episode ------------------------------------------------------------------------------


def test_brains_are_told_the_seed_and_mode_of_an_episode_and_none_of_its_conditions():
    from protocol.episode_spec import WorldVariation
    from protocol.episodes import brain_event, start_event

    conditions = EpisodeSpec(
        circuit="grandprix:31337",
        seed=4242,
        realtime=True,
        world=WorldVariation(line="white"),
        noise=[SaltPepper(probability=0.25)],
        direction="reverse",
        start_m=123.0,
    )
    told = brain_event(start_event("r", 3, conditions))
    assert told == BrainEvent(
        header=Header(run_id="r", episode=3, seq=0, stamp_ns=0),
        kind=EventKind.START,
        seed=4242,
        realtime=True,
        perturbed=True,
    )
    wire = codec.encode(told)
    for condition in (b"grandprix", b"31337", b"white", b"reverse", b"salt"):
        assert condition not in wire, condition
    assert brain_event(EpisodeEvent(header=HEADER, kind=EventKind.END, reason=EndReason.CRASH)) == BrainEvent(
        header=HEADER, kind=EventKind.END
    )
    assert brain_event(EpisodeEvent(header=HEADER, kind=EventKind.LAP, lap=1)) is None  # progress: not theirs
