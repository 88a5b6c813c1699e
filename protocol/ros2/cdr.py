"""CDR as ROS 2 writes it (XCDR1, little endian, plain): the 4-byte encapsulation header ``00 01 00 00``, then the
fields in order, each primitive aligned to its own size (at most 8) counted from after the header; a string is a
uint32 length that counts its NUL, the UTF-8 bytes and the NUL; a sequence a uint32 count and its elements; a fixed
array its elements alone.

A message is a dict of field name to value, nested types as dicts; ``uint8[]`` and ``byte[]`` as ``bytes``. Driven
by the definitions in ``protocol.ros2.interfaces``, so one table gives the hash, the schema text and the bytes.
"""

from __future__ import annotations

import struct
from typing import Any

from protocol.ros2.interfaces import Field, fields

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"
_FORMATS = {
    "bool": "?",
    "byte": "B",
    "char": "B",
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float32": "f",
    "float64": "d",
}
_BYTE_LIKE = frozenset({"uint8", "byte", "char"})


class CdrError(ValueError):
    """Bytes that are not a CDR message of the expected type; the text says where it stopped."""


def encode(type_name: str, message: dict[str, Any]) -> bytes:
    """The CDR bytes (with the encapsulation header) of ``message``, a value of ``type_name``."""
    out = bytearray(ENCAPSULATION_CDR_LE)
    _write_struct(out, type_name, message)
    return bytes(out)


def _align(out: bytearray, size: int) -> None:
    out.extend(b"\x00" * (-(len(out) - 4) % size))


def _write_struct(out: bytearray, type_name: str, message: dict[str, Any]) -> None:
    for field in fields(type_name):
        try:
            value = message[field.name]
        except KeyError:
            raise CdrError(f"{type_name}: no value for field {field.name!r}") from None
        if field.length is None:
            _write_one(out, field.base, value)
        else:
            _write_many(out, field, value)


def _write_one(out: bytearray, base: str, value: Any) -> None:
    if base == "string":
        data = value.encode("utf-8") + b"\x00"
        _align(out, 4)
        out += struct.pack("<I", len(data)) + data
    elif base in _FORMATS:
        fmt = _FORMATS[base]
        _align(out, struct.calcsize(fmt))
        out += struct.pack("<" + fmt, value)
    else:
        _write_struct(out, base, value)


def _write_many(out: bytearray, field: Field, values: Any) -> None:
    if field.length == 0:
        _align(out, 4)
        out += struct.pack("<I", len(values))
    elif len(values) != field.length:
        raise CdrError(f"field {field.name!r} holds {field.length} values, got {len(values)}")
    if field.base in _BYTE_LIKE:
        out += bytes(values)
    elif field.base in _FORMATS and values:
        fmt = _FORMATS[field.base]
        _align(out, struct.calcsize(fmt))
        out += struct.pack(f"<{len(values)}{fmt}", *values)
    else:
        for value in values:
            _write_one(out, field.base, value)


def decode(type_name: str, data: bytes) -> dict[str, Any]:
    """The message of ``type_name`` in CDR bytes ``data`` (little-endian encapsulation only: what ROS 2 writes)."""
    if bytes(data[:4]) != ENCAPSULATION_CDR_LE:
        raise CdrError(f"{type_name}: not little-endian plain CDR (header {bytes(data[:4]).hex()})")
    reader = _Reader(memoryview(data)[4:])
    try:
        return reader.struct(type_name)
    except (struct.error, UnicodeDecodeError, IndexError) as error:
        raise CdrError(f"{type_name}: truncated or malformed at byte {reader.offset + 4} ({error})") from None


class _Reader:
    def __init__(self, data: memoryview) -> None:
        self.data = data
        self.offset = 0

    def _take(self, fmt: str, *, align: int) -> tuple:
        self.offset += -self.offset % align
        values = struct.unpack_from("<" + fmt, self.data, self.offset)
        self.offset += struct.calcsize("<" + fmt)
        return values

    def _bytes(self, length: int) -> bytes:
        if self.offset + length > len(self.data):
            raise IndexError(f"{length} bytes past the end")
        chunk = bytes(self.data[self.offset : self.offset + length])
        self.offset += length
        return chunk

    def struct(self, type_name: str) -> dict[str, Any]:
        return {field.name: self.field(field) for field in fields(type_name)}

    def field(self, field: Field) -> Any:
        if field.length is None:
            return self.one(field.base)
        count = self._take("I", align=4)[0] if field.length == 0 else field.length
        if field.base in _BYTE_LIKE:
            return self._bytes(count)
        if field.base in _FORMATS and count:
            fmt = _FORMATS[field.base]
            return list(self._take(f"{count}{fmt}", align=struct.calcsize(fmt)))
        return [self.one(field.base) for _ in range(count)]

    def one(self, base: str) -> Any:
        if base == "string":
            length = self._take("I", align=4)[0]
            return self._bytes(length)[:-1].decode("utf-8") if length else ""
        if base in _FORMATS:
            fmt = _FORMATS[base]
            return self._take(fmt, align=struct.calcsize(fmt))[0]
        return self.struct(base)
