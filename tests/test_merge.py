"""``drivebench recorder merge``: two runs in one file, each under its own namespace, read back by the official MCAP
reader and the Node validator (the TypeScript reader Foxglove opens files with)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_validation import assert_valid_mcap
from support.recordings import LEGACY, expected_schemas, one_run, write

from protocol import codec
from protocol.mapping import topics
from recorder.merge import MergeError, merge
from recorder.reading import RecordingError, read_messages

ROOT = Path(__file__).resolve().parents[1]


def two_recordings(tmp_path: Path) -> tuple[Path, Path]:
    return (
        write(tmp_path / "a.mcap", one_run("r1", brain="explicit"), run_id="r1"),
        write(tmp_path / "b.mcap", one_run("r2", brain="pilot", steps=30), run_id="r2"),
    )


def read_all(path: Path) -> tuple[dict[str, str], dict[str, list], dict[str, dict[str, str]], dict[str, dict]]:
    """(topic -> schema, topic -> message records, file metadata, topic -> channel metadata), official reader."""
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        channel_metadata = {c.topic: dict(c.metadata) for c in summary.channels.values()}
        messages: dict[str, list] = {}
        for _, channel, message in reader.iter_messages(log_time_order=True):
            messages.setdefault(channel.topic, []).append(message)
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return schemas, messages, metadata, channel_metadata


def test_two_runs_merge_under_their_namespaces_and_share_the_world_frame(tmp_path):
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    a, b = two_recordings(tmp_path)
    report = merge([a, b], output=tmp_path / "ab.mcap")
    schemas, messages, metadata, channel_metadata = read_all(report.output)

    wanted = {}
    for namespace, brain in (("runA", "explicit"), ("runB", "pilot")):
        for topic, schema in expected_schemas(topics.run_topics(brains=(brain,)), image="raw").items():
            wanted[topics.namespaced(topic, namespace)] = schema
    assert schemas == wanted and report.topics == sorted(wanted)
    assert channel_metadata["/runB/camera/truth"]["drivebench.namespace"] == "runB"
    assert channel_metadata["/runB/camera/truth"][topics.RUN_ID_METADATA] == "r2"
    assert_valid_mcap(report.output)

    # Two cars on one circuit: the world frame is shared, each car frame is its run's.
    for namespace, colour in (("runA", (0.1, 0.4, 0.9)), ("runB", (0.95, 0.45, 0.05))):
        transform = FrameTransform.FromString(messages[f"/{namespace}/tf"][-1].data)
        assert (transform.parent_frame_id, transform.child_frame_id) == ("world", f"{namespace}/car")
        assert PoseInFrame.FromString(messages[f"/{namespace}/car/pose"][-1].data).frame_id == "world"
        scene = SceneUpdate.FromString(messages[f"/{namespace}/circuit"][-1].data)
        assert [(e.id, e.frame_id) for e in scene.entities] == [("track", "world"), ("car", f"{namespace}/car")]
        assert (
            scene.entities[1].cubes[0].color.r,
            scene.entities[1].cubes[0].color.g,
            scene.entities[1].cubes[0].color.b,
        ) == pytest.approx(colour)
        assert RawImage.FromString(messages[f"/{namespace}/camera/brain"][0].data).frame_id == f"{namespace}/camera"
    # Both clocks start at 0: the runs play back aligned from their starts.
    assert messages["/runA/camera/truth"][0].log_time == messages["/runB/camera/truth"][0].log_time == 0
    assert len(messages["/runB/camera/truth"]) == 30 and len(messages["/runA/camera/truth"]) == 25

    # File metadata of each run, under its namespace, and what was merged.
    assert metadata["runA/drivebench.run"]["run_id"] == "r1" and metadata["runB/drivebench.run"]["run_id"] == "r2"
    assert metadata["drivebench.merge"]["namespaces"] == '["runA", "runB"]'

    # The bus messages are all there, on their keys, with their extra image fields (run id, seq) intact.
    merged = sorted((r.key, codec.encode(r.message)) for r in read_messages(report.output))
    originals = sorted((r.key, codec.encode(r.message)) for path in (a, b) for r in read_messages(path))
    assert merged == originals


def test_an_old_file_merges_onto_stable_namespaced_topics(tmp_path):
    new = write(tmp_path / "new.mcap", one_run("r1"), run_id="r1")
    report = merge([LEGACY, new], output=tmp_path / "ab.mcap", names=["old", "new"])
    schemas, messages, metadata, _ = read_all(report.output)
    assert {
        "/old/camera/truth",
        "/old/camera/brain",
        "/old/tf",
        "/old/circuit",
        "/old/brain/explicit/cmd",
        "/new/camera/truth",
        "/new/episode/log",
    } <= set(schemas)
    assert not any("legacy1" in topic for topic in schemas)
    assert metadata["drivebench.merge"]["run_ids"] == '{"new": ["r1"], "old": ["legacy1"]}'
    assert_valid_mcap(report.output)


def test_runs_that_share_a_run_id_merge_for_viewing_but_replay_and_datasets_refuse_the_file(tmp_path):
    a = write(tmp_path / "a.mcap", one_run("compose"), run_id="compose")
    b = write(tmp_path / "b.mcap", one_run("compose", steps=10), run_id="compose")
    report = merge([a, b], output=tmp_path / "ab.mcap")
    schemas, messages, _, _ = read_all(report.output)
    assert len(messages["/runA/camera/truth"]) == 25 and len(messages["/runB/camera/truth"]) == 10
    with pytest.raises(
        RecordingError,
        match=r"ab\.mcap: a merged file whose runs /runA and /runB share the run id "
        r"'compose'; replay or build datasets from the original recordings",
    ):
        list(read_messages(report.output))
    assert [r.key for r in read_messages(a, keys_glob="*/scorer/*")]  # the originals read as ever


@pytest.mark.parametrize(
    ("names", "message"),
    [
        (["same", "same"], "must be distinct"),
        (["one"], "1 name(s) for 2 recording(s)"),
        (["a/b", "c"], "namespace 'a/b' may only contain"),
    ],
)
def test_bad_names_are_one_clear_error(tmp_path, names, message):
    a, b = two_recordings(tmp_path)
    with pytest.raises(MergeError, match=re.escape(message)):
        merge([a, b], output=tmp_path / "ab.mcap", names=names)
    assert not (tmp_path / "ab.mcap").exists()


def run_cli(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *argv], capture_output=True, text=True, timeout=120, cwd=ROOT
    )


def test_cli_merges_and_refuses_mistakes_in_one_line(tmp_path):
    a, b = two_recordings(tmp_path)
    out = tmp_path / "ab.mcap"
    result = run_cli("recorder", "merge", str(a), str(b), "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert "/runA <- " in result.stderr and "/runB <- " in result.stderr and out.exists()
    for argv, error in (
        (["recorder", "merge", str(a), str(b), "-o", str(out)], "already exists"),
        (
            ["recorder", "merge", str(a), str(tmp_path / "none.mcap"), "-o", str(tmp_path / "x.mcap")],
            "none.mcap: no such recording",
        ),
        (["recorder", "merge", str(a), "-o", str(tmp_path / "x.mcap")], "at least two"),
        (["recorder", "merge", str(a), str(b), "-o", str(a)], "is one of the inputs"),
    ):
        result = run_cli(*argv)
        assert result.returncode == 2, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1 and error in result.stderr, result.stderr
    assert not (tmp_path / "x.mcap").exists() and not list(tmp_path.glob("*.merging"))
