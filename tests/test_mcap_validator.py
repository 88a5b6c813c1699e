"""The independent MCAP validator (tools/mcap-validate) must pass good files and catch each kind of damage.

Every file here is written by the Python ``mcap`` writer the way drivebench records: zstd, 1 MiB chunks, data CRCs
on, a protobuf ``foxglove.RawImage`` channel and a json channel with a JSON schema.
"""

from __future__ import annotations

import itertools
import json
import random
import struct
import subprocess
import zlib
from pathlib import Path

import pytest
from mcap_validation import SKIP_REASON, VALIDATOR_DIR, assert_valid_mcap, validate_mcap, validator_available
from needs import require

mcap_writer = require("mcap.writer")
mcap_reader = require("mcap.reader")
raw_image_pb2 = require("foxglove_schemas_protobuf.RawImage_pb2")
from protocol.mapping.views import protobuf_schema  # noqa: E402  (the schema the recorder itself writes)

pytestmark = pytest.mark.skipif(not validator_available(), reason=SKIP_REASON)

IMAGES = 300  # 300 random 64x48 RGB frames (~2.8 MB) fill three 1 MiB chunks, so chunk merging is exercised
TELEMETRY = IMAGES  # one telemetry message per image
MSGPACK_BYTES = b"\x81\xa5speed\xcb\x40\x24\x00\x00\x00\x00\x00\x00"  # msgpack for {"speed": 10.0}


def write_recording(path: Path, extra: tuple[str, str, bytes] | None = None, compression: str = "ZSTD") -> Path:
    """A recording like drivebench's; ``extra`` = (topic, message encoding, payload) adds a schemaless channel."""
    rng = random.Random(42)  # deterministic bytes, so byte offsets chosen by the tests are reproducible
    with path.open("wb") as stream:
        writer = mcap_writer.Writer(
            stream, chunk_size=1 << 20, enable_data_crcs=True, compression=mcap_writer.CompressionType[compression]
        )
        writer.start(profile="", library="drivebench-test")
        image_schema = writer.register_schema(
            "foxglove.RawImage", "protobuf", protobuf_schema(raw_image_pb2.RawImage).data
        )
        image_channel = writer.register_channel("/camera/image", "protobuf", image_schema)
        telemetry_schema = writer.register_schema(
            "Telemetry",
            "jsonschema",
            json.dumps(
                {"type": "object", "properties": {"speed": {"type": "number"}, "seq": {"type": "integer"}}}
            ).encode(),
        )
        telemetry_channel = writer.register_channel("/telemetry", "json", telemetry_schema)
        extra_channel = writer.register_channel(extra[0], extra[1], 0) if extra else None
        for i in range(IMAGES):  # interleaved, as a live recording is: every chunk holds every channel
            t = 1_000_000_000 + i * 50_000_000
            image = raw_image_pb2.RawImage(
                width=64, height=48, encoding="rgb8", step=64 * 3, frame_id="camera", data=rng.randbytes(64 * 48 * 3)
            )
            image.timestamp.FromNanoseconds(t)
            writer.add_message(image_channel, t, image.SerializeToString(), t, sequence=i)
            writer.add_message(
                telemetry_channel, t + 1, json.dumps({"speed": 10.0, "seq": i}).encode(), t + 1, sequence=i
            )
            if extra_channel is not None:
                writer.add_message(extra_channel, t + 2, extra[2], t + 2, sequence=i)
        writer.finish()
    return path


def run_cli(*args: str | Path) -> subprocess.CompletedProcess:
    """The validator as a user runs it, to check its text output and exit code directly."""
    return subprocess.run(
        ["node", str(VALIDATOR_DIR / "validate.mjs"), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def chunk_offsets(path: Path) -> list[tuple[int, int]]:
    """(start, length) of every chunk record, from the file's own chunk index."""
    with path.open("rb") as stream:
        summary = mcap_reader.make_reader(stream).get_summary()
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def damage(path: Path, offset: int, new_bytes: bytes | None = None) -> Path:
    """Overwrite bytes at ``offset`` (default: invert one byte) in place."""
    data = bytearray(path.read_bytes())
    replacement = new_bytes if new_bytes is not None else bytes([data[offset] ^ 0xFF])
    data[offset : offset + len(replacement)] = replacement
    path.write_bytes(bytes(data))
    return path


def records(data: bytes, start: int, end: int):
    """(offset, opcode) of each top-level record from ``start`` to ``end``: opcode u8, content length u64."""
    while start < end:
        yield start, data[start]
        start += 9 + int.from_bytes(data[start + 1 : start + 9], "little")


@pytest.fixture
def good(tmp_path) -> Path:
    return write_recording(tmp_path / "good.mcap")


def test_good_file_passes_with_decode_and_viewable(good):
    result = assert_valid_mcap(good)  # decode and require_viewable are on by default
    [file] = result.files
    assert (file.ok, file.truncated, file.messages, file.channels) == (True, False, IMAGES + TELEMETRY, 2)
    assert len(chunk_offsets(good)) >= 3, "the file should span several chunks"
    cli = run_cli("--decode", "--require-viewable", good)
    assert (cli.returncode, cli.stdout.strip()) == (0, f"OK {good}: {IMAGES + TELEMETRY} messages, 2 channels")


@pytest.mark.parametrize("compression", ["NONE", "LZ4"])
def test_other_compressions_pass(tmp_path, compression):
    path = write_recording(tmp_path / f"{compression}.mcap", compression=compression)
    assert validate_mcap(path).files[0].messages == IMAGES + TELEMETRY
    assert_valid_mcap(path)


def test_truncated_file_exits_2(good):
    data = good.read_bytes()
    good.write_bytes(data[: len(data) // 2])
    result = validate_mcap(good)
    [file] = result.files
    assert (result.returncode, file.ok, file.truncated) == (2, False, True)
    assert file.errors[0].startswith("truncated"), file.errors
    assert run_cli(good).returncode == 2


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_flipped_byte_inside_chunk_is_an_error(good, fraction):
    start, length = chunk_offsets(good)[1]
    damage(good, start + int(length * fraction))
    result = validate_mcap(good)
    [file] = result.files
    assert (result.returncode, file.ok, file.truncated) == (1, False, False), file.errors
    assert file.errors


def test_corrupt_record_length_is_an_error_not_a_truncation(good):
    # A chunk's length field (after its 1-byte opcode) now points past the end of the file: the stream reader
    # waits for bytes that never come, which looks like truncation unless the trailing magic is noticed.
    start, _ = chunk_offsets(good)[0]
    damage(good, start + 1, (1 << 40).to_bytes(8, "little"))
    result = validate_mcap(good)
    assert (result.returncode, result.files[0].truncated) == (1, False), result.files[0].errors


def test_flipped_header_byte_is_caught_by_the_data_section_crc(good):
    # Nothing but DataEnd's data_section_crc covers the Header record: @mcap/core never checks it, the validator must.
    offset = good.read_bytes().index(b"drivebench-test")
    damage(good, offset, b"X")
    [file] = validate_mcap(good).files
    assert not file.ok
    assert any("data section CRC" in e for e in file.errors), file.errors


def test_message_index_naming_the_wrong_channel_is_an_error(good):
    # @mcap/core trusts a MessageIndex's channel id; a viewer showing "/camera/image" would then get telemetry.
    # Relabel the first chunk's second MessageIndex (telemetry) with the first one's channel (images).
    data = bytearray(good.read_bytes())
    start, length = chunk_offsets(good)[0]
    after_chunk = records(data, start + length, len(data))
    first, second = [offset for offset, _ in itertools.takewhile(lambda r: r[1] == 0x07, after_chunk)]  # MessageIndex
    data[second + 9 : second + 11] = data[first + 9 : first + 11]  # channel_id u16 follows opcode and length
    good.write_bytes(bytes(data))
    [file] = validate_mcap(good).files
    assert any('"/camera/image"' in e and "belong to another topic" in e for e in file.errors), file.errors


def test_statistics_that_lie_are_an_error(good):
    # The Python writer always counts right, so play a buggy writer: bump Statistics.message_count (its first
    # field) and re-sign the summary so that only the count, not the summary CRC, is wrong.
    data = bytearray(good.read_bytes())
    footer = len(data) - 8 - 29  # Footer: opcode, length, summary_start, summary_offset_start, summary_crc; magic
    summary_start = int.from_bytes(data[footer + 9 : footer + 17], "little")
    statistics = next(o for o, op in records(data, summary_start, footer) if op == 0x0B)
    struct.pack_into("<Q", data, statistics + 9, IMAGES + TELEMETRY + 1)
    struct.pack_into("<I", data, footer + 25, zlib.crc32(data[summary_start : footer + 25]))
    good.write_bytes(bytes(data))
    [file] = validate_mcap(good).files
    assert file.errors == [f"Statistics messageCount is {IMAGES + TELEMETRY + 1}, actual {IMAGES + TELEMETRY}"]


def test_msgpack_channel_is_an_error_only_when_viewable_is_required(tmp_path):
    path = write_recording(tmp_path / "msgpack.mcap", extra=("/debug/state", "msgpack", MSGPACK_BYTES))
    assert validate_mcap(path, decode=True, require_viewable=False).ok
    result = validate_mcap(path, decode=True, require_viewable=True)
    assert result.returncode == 1
    assert any('"/debug/state"' in e and "msgpack" in e for e in result.files[0].errors), result.files[0].errors


def test_non_json_bytes_on_a_json_channel_are_an_error_only_when_decoding(tmp_path):
    # The bug this validator first caught: msgpack bytes published on a channel declared "json".
    path = write_recording(tmp_path / "badjson.mcap", extra=("/debug/state", "json", MSGPACK_BYTES))
    assert validate_mcap(path, decode=False, require_viewable=True).ok
    result = validate_mcap(path, decode=True, require_viewable=True)
    assert result.returncode == 1
    [error] = result.files[0].errors
    assert '"/debug/state"' in error and f"{TELEMETRY} of {TELEMETRY}" in error and "sequence 0" in error


def test_protobuf_bytes_that_do_not_match_the_schema_are_an_error(tmp_path):
    # 0xFF starts a field with wire type 7, which does not exist: protobufjs must reject it.
    bad = tmp_path / "badproto.mcap"
    with bad.open("wb") as stream:
        writer = mcap_writer.Writer(stream, enable_data_crcs=True)
        writer.start()
        schema = writer.register_schema("foxglove.RawImage", "protobuf", protobuf_schema(raw_image_pb2.RawImage).data)
        channel = writer.register_channel("/camera/image", "protobuf", schema)
        writer.add_message(channel, 1, b"\xff\xff\xff", 1, sequence=7)
        writer.finish()
    [file] = validate_mcap(bad).files
    assert not file.ok
    assert any('"/camera/image"' in e and "sequence 7" in e for e in file.errors), file.errors


def test_bad_usage_and_missing_files_print_one_line_without_stack_trace(tmp_path):
    usage = run_cli()
    assert (usage.returncode, usage.stdout) == (1, "")
    assert usage.stderr.count("\n") == 1 and "usage:" in usage.stderr
    missing = run_cli(tmp_path / "nope.mcap")
    assert missing.returncode == 1
    assert missing.stdout.startswith(f"ERROR {tmp_path / 'nope.mcap'}:") and missing.stdout.count("\n") == 1
    assert missing.stderr == ""
