"""MessagePack encoding of the bus messages, and checked decoding into an expected type.

Decoding always names the type expected, so a wrong or damaged payload fails at the boundary with the field path
(``$.header.seq``) in the error, instead of deep inside a service. Never pickle.
"""

from __future__ import annotations

from typing import Any, TypeVar

import msgspec

T = TypeVar("T")

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[Any, msgspec.msgpack.Decoder] = {}


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected type; the text names the field path."""


def encode(message: msgspec.Struct) -> bytes:
    return _encoder.encode(message)


def decode(data: bytes | bytearray | memoryview, message_type: type[T]) -> T:
    """Decode ``data`` as ``message_type``; raise :class:`DecodeError` naming the type and the bad field."""
    decoder = _decoders.get(message_type)
    if decoder is None:
        decoder = _decoders[message_type] = msgspec.msgpack.Decoder(message_type)
    try:
        return decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as error:
        raise DecodeError(f"not a valid {getattr(message_type, '__name__', message_type)}: {error}") from None


def to_builtins(message: msgspec.Struct) -> Any:
    """Plain dicts / lists / numbers for JSON output (bytes become base64)."""
    return msgspec.to_builtins(message)


def to_json(message: Any, *, indent: int = 0) -> str:
    text = msgspec.json.encode(message)
    if indent:
        text = msgspec.json.format(text, indent=indent)
    return text.decode()
