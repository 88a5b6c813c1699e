"""JSON Schemas of the messages a brain process exchanges, generated from the message types themselves.

On the wire every message is a MessagePack *map* whose keys are the field names below, with a ``type`` field naming
the message and its version (``drivebench.CameraFrame.v1``). The schemas describe that map; where JSON Schema says
"string, base64" for ``bytes`` (``CameraFrame.data``), MessagePack carries raw ``bin`` instead: each such field is
marked ``"x-msgpack": "bin"``. ``docs/brain-protocol.md`` explains keys, timing and liveliness around them.

``drivebench brains schema`` writes them to ``docs/protocol/``; a test keeps the committed files current.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec

from protocol.messages import BrainEvent, CameraFrame, Command, ControlReply, ControlRequest, EpisodeEvent, Pose

# What a brain process reads (frames; the brains' events for the seed; the whole events and ground truth for
# trusted and privileged brains; control requests) and writes (commands; control replies).
BRAIN_MESSAGES: tuple[type[msgspec.Struct], ...] = (
    CameraFrame,
    Command,
    BrainEvent,
    EpisodeEvent,
    ControlRequest,
    ControlReply,
    Pose,
)


def message_schema(message_type: type[msgspec.Struct]) -> dict[str, Any]:
    """The JSON Schema of one message type, as its MessagePack map (``bytes`` fields marked as msgpack bin)."""
    schema = msgspec.json.schema(message_type)
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://drivebench.dev/protocol/{message_type.__name__}.schema.json",
        **schema,
    }
    return _mark_bin(schema)


def _mark_bin(node: Any) -> Any:
    if isinstance(node, dict):
        if node.get("contentEncoding") == "base64":
            return {
                **node,
                "x-msgpack": "bin",
                "description": "raw bytes: MessagePack bin on the wire (base64 only in JSON)",
            }
        return {key: _mark_bin(value) for key, value in node.items()}
    if isinstance(node, list):
        return [_mark_bin(item) for item in node]
    return node


def schema_files() -> dict[str, str]:
    """File name -> text of every brain message's schema."""
    return {
        f"{message.__name__}.schema.json": json.dumps(message_schema(message), indent=2) + "\n"
        for message in BRAIN_MESSAGES
    }


def write_schemas(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in schema_files().items():
        path = folder / name
        path.write_text(text)
        written.append(path)
    return written
