"""Live swap and shadow brains, the pure parts: message fields, matching commands by frame, finding a stack, report."""

from __future__ import annotations

import json
import os

import msgpack
import pytest
from support.messages import METRICS  # one set of example metrics for the message tests

from orchestrator.cli.run import shadow_launches
from orchestrator.cli.swap import brain_options
from orchestrator.report.episode import metrics_table
from orchestrator.stack.launcher import BrainLaunch
from orchestrator.stack.swap import BrainIdentity, StackInfo, SwapError, _pick_name, locate_stack
from protocol import codec, keys
from protocol.deploy.runtime import UsageError
from protocol.episode_spec import EpisodeSpec
from protocol.mapping.recording import channel_layout, from_record, to_record
from protocol.messages import (
    BrainSwitch,
    Command,
    ControlReply,
    ControlRequest,
    EndReason,
    EpisodeScore,
    Header,
    ShadowDistance,
)
from services.scorer.shadows import CommandMatcher

HEADER = Header(run_id="r1", episode=0, seq=0, stamp_ns=1_000_000_000)
SCORE = EpisodeScore(
    header=HEADER,
    spec=EpisodeSpec(),
    reason=EndReason.TIME_LIMIT,
    brain="explicit-2",
    metrics=METRICS,
    switches=[BrainSwitch(stamp_ns=150_000_000, seq=3, from_brain="explicit", to_brain="explicit-2")],
    shadows=[
        ShadowDistance(
            brain="constant",
            frames=18,
            speed_mae_mps=6.0,
            yaw_rate_mae_radps=0.25,
            yaw_rate_rmse_radps=0.3,
            yaw_rate_max_abs_radps=0.9,
        )
    ],
)


# -- protocol ---------------------------------------------------------------------------------------------------------


def test_a_score_without_switches_and_shadows_still_decodes():
    """Scores written before switches and shadows existed (no such keys) decode with empty lists."""
    old = msgpack.unpackb(codec.encode(SCORE), raw=False)
    del old["switches"], old["shadows"]
    score = codec.decode(msgpack.packb(old), EpisodeScore)
    assert score.switches == [] and score.shadows == []
    assert codec.decode(codec.encode(SCORE), EpisodeScore) == SCORE


def test_control_messages_carry_the_switch_and_the_running_spec():
    request = ControlRequest(action="switch", brain="explicit-2")
    assert codec.decode(codec.encode(request), ControlRequest) == request
    reply = ControlReply(ok=True, state="running", episode=2, active_brain="explicit", spec=EpisodeSpec(seed=5))
    assert codec.decode(codec.encode(reply), ControlReply) == reply
    assert (
        codec.decode(msgpack.packb({"type": "drivebench.ControlRequest.v1", "action": "status"}), ControlRequest).brain
        == ""
    )


def test_brain_control_key():
    assert keys.brain_control("r1", "explicit-2") == "drivebench/run/r1/brain/explicit-2/control"
    with pytest.raises(ValueError):
        keys.brain_control("r1", "a/b")


def test_a_score_with_switches_and_shadows_is_recorded_and_read_back():
    layout = channel_layout(keys.score("r1"), EpisodeScore)
    assert from_record(to_record(SCORE), schema_name=layout.schema.name, metadata=layout.metadata) == SCORE
    schema = json.loads(layout.schema.data)
    switch_fields = schema["properties"]["switches"]["items"]["properties"]
    assert {"stamp_ns", "seq", "from_brain", "to_brain"} <= set(switch_fields)
    assert "yaw_rate_mae_radps" in schema["properties"]["shadows"]["items"]["properties"]
    assert "$ref" not in json.dumps(schema)


# -- matching commands by frame ---------------------------------------------------------------------------------------


def command(
    brain: str, frame_seq: int, speed_mps: float = 1.0, yaw_rate_radps: float = 0.0, *, host: str = ""
) -> Command:
    """A command of ``brain``; ``host`` given: from a brain host started as a shadow, that process."""
    return Command(
        header=Header(run_id="r", episode=0, seq=frame_seq, stamp_ns=frame_seq * 50_000_000),
        brain=brain,
        frame_seq=frame_seq,
        speed_mps=speed_mps,
        yaw_rate_radps=yaw_rate_radps,
        shadow=bool(host),
        host=host or f"{brain}-host",
    )


def test_the_driver_of_each_frame_follows_the_switches_whatever_arrives_first():
    driven: list[tuple[str, int]] = []
    matcher = CommandMatcher(first_driver="a", on_driver=lambda c: driven.append((c.brain, c.frame_seq)))
    for frame in range(6):
        matcher.add_command(command("a", frame))
        matcher.add_command(command("b", frame, speed_mps=2.0))
    # The switch event arrives after the commands around it: nothing is settled yet, so nothing is misattributed.
    matcher.add_switch(BrainSwitch(stamp_ns=150_000_000, seq=3, from_brain="a", to_brain="b"))
    shadows = matcher.finish()
    assert driven == [("a", 0), ("a", 1), ("a", 2), ("b", 3), ("b", 4), ("b", 5)]
    assert shadows == []  # brains swapped in or out are not shadows (issue 34: they were listed as such)
    assert [s.to_brain for s in matcher.switches] == ["b"]


def test_each_shadow_process_is_its_own_entry_even_under_one_name():
    """Issue 34: two shadow processes of one name were merged into one entry (keyed by name)."""
    matcher = CommandMatcher(first_driver="d", on_driver=lambda c: None)
    for frame in range(4):
        matcher.add_command(command("d", frame, yaw_rate_radps=0.0))
        matcher.add_command(command("twin", frame, yaw_rate_radps=0.1, host="host-1"))
        matcher.add_command(command("twin", frame, yaw_rate_radps=-0.3, host="host-2"))
        matcher.add_command(command("d", frame, yaw_rate_radps=2.0, host="host-3"))  # a shadow under the driver's name
        matcher.add_command(command("idle", frame, yaw_rate_radps=1.0))  # running, not a shadow: waits for a swap
    shadows = {(s.brain, s.host): s for s in matcher.finish()}
    assert set(shadows) == {("twin", "host-1"), ("twin", "host-2"), ("d", "host-3")}
    assert shadows["twin", "host-1"].yaw_rate_mae_radps == pytest.approx(0.1)
    assert shadows["twin", "host-2"].yaw_rate_mae_radps == pytest.approx(0.3)
    assert shadows["d", "host-3"].yaw_rate_mae_radps == pytest.approx(2.0)  # compared with the driver, never it


def test_shadow_distances_count_only_frames_both_answered():
    matcher = CommandMatcher(first_driver="d", on_driver=lambda c: None)
    for frame, (w_driver, w_shadow) in enumerate([(0.0, 0.3), (0.1, -0.3), (0.2, 0.2)]):
        matcher.add_command(command("d", frame, yaw_rate_radps=w_driver))
        matcher.add_command(command("s", frame, yaw_rate_radps=w_shadow, host="s1"))
        matcher.add_command(command("s", frame, yaw_rate_radps=99.0, host="s1"))  # a repeated answer: the first counts
    matcher.add_command(command("s", 3, yaw_rate_radps=5.0, host="s1"))  # the driver never answered frame 3
    [shadow] = matcher.finish()
    assert shadow.brain == "s" and shadow.frames == 3
    assert shadow.yaw_rate_mae_radps == pytest.approx((0.3 + 0.4 + 0.0) / 3)
    assert shadow.yaw_rate_rmse_radps == pytest.approx(((0.09 + 0.16) / 3) ** 0.5)
    assert shadow.yaw_rate_max_abs_radps == pytest.approx(0.4)
    assert shadow.speed_mae_mps == 0.0


def test_pending_frames_are_bounded():
    driven = []
    matcher = CommandMatcher(first_driver="d", on_driver=driven.append, max_pending_frames=10)
    for frame in range(100):
        matcher.add_command(command("d", frame))
    assert len(driven) == 90  # the oldest settled as new ones came
    matcher.add_command(command("s", 5, host="s1"))  # too late: its frame is settled
    assert matcher.late_commands == 1
    assert matcher.finish() == [] and len(driven) == 100


# -- finding the stack, names, options --------------------------------------------------------------------------------


def write_stack(folder, *, run_id: str, pid: int, router: str = "tcp/127.0.0.1:7447"):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "stack.json").write_text(json.dumps({"router": router, "run_id": run_id, "pid": pid}))
    return folder


def test_locate_stack_takes_the_newest_live_one(tmp_path):
    write_stack(tmp_path / "a", run_id="old", pid=os.getpid(), router="tcp/127.0.0.1:1")
    newest = write_stack(tmp_path / "b", run_id="new", pid=os.getpid(), router="tcp/127.0.0.1:2")
    os.utime(newest / "stack.json", (2e9, 2e9))
    write_stack(tmp_path / "c", run_id="dead", pid=2**22 + 1)
    assert locate_stack(runs_dir=tmp_path, run_id=None, router=None) == StackInfo("tcp/127.0.0.1:2", "new", newest)
    assert locate_stack(runs_dir=tmp_path, run_id="old", router=None).router == "tcp/127.0.0.1:1"
    assert locate_stack(runs_dir=tmp_path, run_id="old", router="tcp/h:9").router == "tcp/h:9"
    assert locate_stack(runs_dir=tmp_path, run_id="elsewhere", router="tcp/h:9") == StackInfo("tcp/h:9", "elsewhere")
    with pytest.raises(SwapError, match="no running run dead found"):
        locate_stack(runs_dir=tmp_path, run_id="dead", router=None)


def test_new_brain_names_avoid_the_alive_ones():
    assert _pick_name("explicit", None, {"constant"}, run_id="r") == "explicit"
    assert _pick_name("explicit", None, {"explicit", "explicit-2"}, run_id="r") == "explicit-3"
    assert _pick_name("explicit", "mine", {"explicit"}, run_id="r") == "mine"
    with pytest.raises(UsageError, match="already alive"):
        _pick_name("explicit", "explicit", {"explicit"}, run_id="r")
    with pytest.raises(UsageError, match="may only contain"):
        _pick_name("explicit", "a b", set(), run_id="r")


def test_swap_options_check_the_weights_file(tmp_path):
    assert brain_options(["speed_mps=2"], None) == ("speed_mps=2",)
    with pytest.raises(UsageError, match="no such file"):
        brain_options([], tmp_path / "missing.ckpt")
    with pytest.raises(UsageError, match="KEY=VALUE"):
        brain_options(["speed"], None)
    weights = tmp_path / "w.ckpt"
    weights.write_bytes(b"x")
    assert brain_options([], weights) == (f"weights={json.dumps(str(weights.resolve()))}",)


def test_a_brain_identity_is_checked_and_becomes_the_brain_hosts_bus_settings(tmp_path):
    cert, key, password = tmp_path / "brain.pem", tmp_path / "brain.key", tmp_path / "pw"
    for path in (cert, key, password):
        path.write_text("x")
    with pytest.raises(UsageError, match="--brain-cert: no such file"):
        BrainIdentity(tls_cert=tmp_path / "none.pem", tls_key=key)
    with pytest.raises(UsageError, match="--brain-cert and --brain-key go together"):
        BrainIdentity(tls_cert=cert)
    with pytest.raises(UsageError, match="--brain-user and --brain-password-file go together"):
        BrainIdentity(user="pilot")
    assert BrainIdentity(tls_cert=cert, tls_key=key, user="pilot", password_file=password).overrides() == [
        "--set",
        f"bus.tls_cert={json.dumps(str(cert))}",
        "--set",
        f"bus.tls_key={json.dumps(str(key))}",
        "--set",
        'bus.user="pilot"',
        "--set",
        f"bus.password_file={json.dumps(str(password))}",
    ]


def test_name_claims_round_trip_names_with_dots():
    key = keys.name_claim("r1", "my.brain-2", "abc123")
    assert key == "drivebench/alive/r1/claim/my.brain-2.abc123"
    assert keys.parse_name_claim(key) == ("my.brain-2", "abc123")


def test_shadow_names_never_clash():
    launches = shadow_launches(["explicit", "constant", "explicit"], taken={"explicit"})
    assert [launch.bus_name for launch in launches] == ["explicit-shadow1", "constant", "explicit-shadow2"]
    assert launches[0] == BrainLaunch("explicit", name="explicit-shadow1", host=("shadow=true",))  # started as one
    with pytest.raises(UsageError, match="unknown brain 'hal'"):
        shadow_launches(["hal"], taken=set())


def test_the_metrics_table_shows_switches_and_shadows():
    table = metrics_table(SCORE)
    assert "explicit -> explicit-2 at frame 3 (0.15 s)" in table
    assert "shadow constant" in table and "0.250 / 0.300 / 0.900 rad/s over 18 frames" in table
    plain = metrics_table(
        EpisodeScore(header=HEADER, spec=EpisodeSpec(), reason=EndReason.TIME_LIMIT, brain="explicit", metrics=METRICS)
    )
    assert "switch" not in plain and "shadow" not in plain
