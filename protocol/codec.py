"""MessagePack encoding of the bus messages, and checked decoding into an expected type.

Decoding always names the type expected, so a wrong or damaged payload fails at the boundary with the field path
(``$.header.seq``) in the error, instead of deep inside a service. Never pickle.

One rule holds for every message type: a float is finite. MessagePack carries NaN and infinities, and one of them
passes through arithmetic silently until something (a spline, ``int()``, an exponent) fails far from its source, so
:func:`decode` rejects them like any other bad field, naming its path.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, TypeVar

import msgspec

if TYPE_CHECKING:
    # PEP 747: a type expression as a value, so that a union of tagged structs (``RunMessage``) decodes typed as
    # well as one struct. typing_extensions is only read by the type checker here (mypy ships its stub).
    from typing_extensions import TypeForm

T = TypeVar("T")

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[Any, msgspec.msgpack.Decoder] = {}


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected type; the text names the field path."""


def encode(message: msgspec.Struct) -> bytes:
    return _encoder.encode(message)


def decode(data: bytes | bytearray | memoryview, message_type: TypeForm[T]) -> T:
    """Decode ``data`` as ``message_type``; raise :class:`DecodeError` naming the type and the bad field."""
    decoder = _decoders.get(message_type)
    if decoder is None:
        decoder = _decoders[message_type] = msgspec.msgpack.Decoder(message_type)
    name = getattr(message_type, "__name__", message_type)
    try:
        message = decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as error:
        raise DecodeError(f"not a valid {name}: {error}") from None
    if (found := non_finite(message)) is not None:
        path, value = found
        raise DecodeError(f"not a valid {name}: Expected a finite `float`, got {value} - at `{path}`")
    return message


def non_finite(value: Any, path: str = "$") -> tuple[str, float] | None:
    """(path, value) of the first NaN or infinite float in a decoded message (structs, lists, dicts), or None."""
    if isinstance(value, float):
        return None if math.isfinite(value) else (path, value)
    if isinstance(value, msgspec.Struct):
        items: Any = ((f"{path}.{name}", getattr(value, name)) for name in value.__struct_fields__)
    elif isinstance(value, (list, tuple)):
        items = ((f"{path}[{index}]", item) for index, item in enumerate(value))
    elif isinstance(value, dict):
        items = ((f"{path}[{key!r}]", item) for key, item in value.items())
    else:
        return None
    for item_path, item in items:
        if (found := non_finite(item, item_path)) is not None:
            return found
    return None


def to_builtins(message: msgspec.Struct) -> Any:
    """Plain dicts / lists / numbers for JSON output (bytes become base64)."""
    return msgspec.to_builtins(message)


def to_json(message: Any, *, indent: int = 0) -> str:
    text = msgspec.json.encode(message)
    if indent:
        text = msgspec.json.format(text, indent=indent)
    return text.decode()
