"""``recorder info`` and ``replay`` on files that are not one drivebench run: another tool's MCAP file, and a merged
file of two real recorded runs (real stacks, real recorder, ``drivebench recorder merge``), through the real CLI."""

from __future__ import annotations

import json
import signal
import time
import uuid
from pathlib import Path

import pytest
from mcap.writer import Writer
from support.recorder import run_cli, start_recorder

from orchestrator.stack.launcher import BrainLaunch, LocalStack, free_loopback_port
from protocol import keys
from protocol.bus import Bus, BusConfig
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.messages import EndReason
from recorder.reading import read_messages, recording_info

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def merged(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """(merged file, namespace -> run id) of two 1 s runs recorded by real stacks."""
    folder = tmp_path_factory.mktemp("runs")
    runs = {}
    for namespace, circuit in (("runA", "simple"), ("runB", "many_curves")):
        run_id = f"t{uuid.uuid4().hex[:8]}"
        with LocalStack(
            run_id=run_id,
            run_dir=folder / run_id,
            brains=[BrainLaunch("explicit")],
            record=folder / f"{namespace}.mcap",
        ) as stack:
            spec = EpisodeSpec(circuit=circuit, max_sim_seconds=1.0, camera=CameraSpec(width_px=64, height_px=48))
            assert stack.run_episode(spec).reason == EndReason.TIME_LIMIT
        runs[namespace] = run_id
    result = run_cli(
        "recorder", "merge", str(folder / "runA.mcap"), str(folder / "runB.mcap"), "-o", str(folder / "ab.mcap")
    )
    assert result.returncode == 0, result.stderr
    return folder / "ab.mcap", runs


def test_info_calls_another_tools_channels_other_not_view(tmp_path):
    path = tmp_path / "imu.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema("Imu", "jsonschema", b'{"type": "object"}')
        channel = writer.register_channel("/imu", "json", schema)
        for i in range(3):
            writer.add_message(channel, log_time=i, data=b'{"ax": 0}', publish_time=i)
        writer.finish()
    info = run_cli("recorder", "info", str(path))
    assert info.returncode == 0, info.stderr
    [line] = [line for line in info.stdout.splitlines()[1:] if "/imu" in line]
    assert line.split()[0] == "other", line


def test_info_lists_the_episodes_of_each_run_of_a_merged_file(merged):
    path, runs = merged
    info = run_cli("recorder", "info", str(path))
    assert info.returncode == 0, info.stderr
    episodes = [line.strip() for line in info.stdout.splitlines() if "episode:" in line]
    assert len(episodes) == 2, info.stdout
    assert episodes[0].startswith("/runA episode:0:") and runs["runA"] in episodes[0] and "simple" in episodes[0]
    assert episodes[1].startswith("/runB episode:0:") and runs["runB"] in episodes[1] and "many_curves" in episodes[1]
    assert not [line for line in info.stdout.splitlines() if line.split()[0] == "other"]  # all of it is drivebench's


def test_replay_refuses_to_fold_the_runs_of_a_merged_file_into_one(merged):
    path, runs = merged
    result = run_cli("replay", str(path), "--router", "tcp/127.0.0.1:9", "--run-id", "folded")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert "2 runs" in result.stderr and runs["runA"] in result.stderr and runs["runB"] in result.stderr


def test_replay_of_one_run_of_a_merged_file_under_a_new_id(merged, tmp_path):
    path, runs = merged
    with Bus(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{free_loopback_port()}"]), name="router") as bus:
        endpoint = bus.config.listen[0]
        recorder = start_recorder(endpoint, bus, "onlyb", tmp_path / "b.mcap")
        run_b = f"drivebench/run/{runs['runB']}/*"
        result = run_cli("replay", str(path), "--router", endpoint, "--run-id", "onlyb", "--keys", run_b, "--max-speed")
        assert result.returncode == 0, result.stderr
        time.sleep(1.0)
        recorder.send_signal(signal.SIGTERM)
        assert recorder.wait(timeout=30) == 128 + signal.SIGTERM
    original = [r for r in read_messages(path) if r.key.startswith(f"drivebench/run/{runs['runB']}/")]
    replayed = list(read_messages(tmp_path / "b.mcap"))
    assert len(replayed) == len(original) > 0
    assert {keys.run_of_key(r.key) for r in replayed} == {"onlyb"}
    assert {c.run_id for c in recording_info(tmp_path / "b.mcap").channels if c.bus_key} == {"onlyb"}
    spec = json.loads(recording_info(tmp_path / "b.mcap").metadata["episode:0"]["spec"])
    assert spec["circuit"] == "many_curves"
