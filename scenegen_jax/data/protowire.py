"""A small reader of the protocol buffer wire format, driven by a schema of ours.

It decodes only what a schema names (other fields are skipped, as protobuf's parsers skip
unknown fields), so a reader of a data set's messages needs neither protoc nor generated
classes. A `Message` maps field numbers to `Field`s (name, kind, repeated); a kind is a
scalar name of `SCALAR_KINDS` or a nested `Message`. Decoded messages are dicts by field
name; an absent optional field is absent from the dict (callers choose what it means), an
absent repeated field is an empty list. Repeated numbers are read packed or unpacked, as the
wire format allows either for the same field. The last occurrence of an optional field wins.

Encoding (https://protobuf.dev/programming-guides/encoding/): each field is a varint key,
`number << 3 | wire type`, then a varint (type 0), 8 little-endian bytes (type 1), a varint
length and that many bytes (type 2), or 4 little-endian bytes (type 5).
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any, NamedTuple

VARINT, I64, LEN, I32 = 0, 1, 2, 5
SCALAR_KINDS = ("double", "float", "int", "uint", "bool", "string", "bytes")
_DOUBLE, _FLOAT = struct.Struct("<d"), struct.Struct("<f")
_WIRE_OF_KIND = {"double": I64, "float": I32, "int": VARINT, "uint": VARINT, "bool": VARINT,
                 "string": LEN, "bytes": LEN}


class Field(NamedTuple):
    """A field of a message: its name, its kind (a scalar name or a nested `Message`) and
    whether it repeats."""

    name: str
    kind: str | Message
    repeated: bool = False


class Message:
    """A message schema: its fields by number, and the field of each wire key, computed
    once (the decoder looks keys up, not numbers and wire types)."""

    def __init__(self, fields: Mapping[int, Field]):
        self.fields = dict(fields)
        self.repeated = tuple(f.name for f in self.fields.values() if f.repeated)
        self.by_key: dict[int, tuple[Field, bool]] = {}  # key -> (field, packed)
        for number, field in self.fields.items():
            if not isinstance(field.kind, Message) and field.kind not in SCALAR_KINDS:
                raise ValueError(f"field {field.name}: unknown kind {field.kind!r}")
            wire = LEN if isinstance(field.kind, Message) else _WIRE_OF_KIND[field.kind]
            self.by_key[number << 3 | wire] = (field, False)
            if field.repeated and wire != LEN:
                self.by_key[number << 3 | LEN] = (field, True)


class WireError(ValueError):
    """Damaged or foreign bytes; `field` is the dotted path of the field being read."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}" if field else message)
        self.field, self.message = field, message

    def inside(self, outer: str) -> WireError:
        return WireError(f"{outer}.{self.field}" if self.field else outer, self.message)


def read_varint(buf: bytes, pos: int, end: int) -> tuple[int, int]:
    """(value, position after it) of the varint at `pos`; at most 10 bytes, before `end`."""
    result = shift = 0
    while pos < end:
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7
        if shift >= 70:
            raise WireError("", "varint longer than 10 bytes")
    raise WireError("", "truncated varint")


def _from_varint(kind: str, value: int) -> Any:
    """int32 / int64 values are sent as 64-bit two's complement varints."""
    if kind == "int":
        return value - (1 << 64) if value >= 1 << 63 else value
    return value != 0 if kind == "bool" else value


def _packed(buf: bytes, start: int, stop: int, kind: str) -> list:
    """The values of a packed repeated number field occupying buf[start:stop]."""
    if kind in ("double", "float"):
        size = 8 if kind == "double" else 4
        if (stop - start) % size:
            raise WireError("", f"packed {kind}s: {stop - start} bytes, not a multiple of {size}")
        fmt = f"<{(stop - start) // size}{'d' if kind == 'double' else 'f'}"
        return list(struct.unpack_from(fmt, buf, start))
    out, pos = [], start
    while pos < stop:
        value, pos = read_varint(buf, pos, stop)
        out.append(_from_varint(kind, value))
    return out


def _skip(buf: bytes, pos: int, end: int, wire: int) -> int:
    """Position after the value of an unused field of wire type `wire` at `pos`."""
    if wire == VARINT:
        return read_varint(buf, pos, end)[1]
    if wire == I64:
        pos += 8
    elif wire == I32:
        pos += 4
    elif wire == LEN:
        size, pos = read_varint(buf, pos, end)
        pos += size
    else:  # groups (3, 4) are deprecated and absent from the schemas we read; 6, 7 are invalid
        raise WireError("", f"unsupported wire type {wire}")
    if pos > end:
        raise WireError("", "runs past the end of its message")
    return pos


def _bytes_value(buf: bytes, start: int, stop: int, kind: str) -> str | bytes:
    raw = bytes(buf[start:stop])
    if kind == "bytes":
        return raw
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise WireError("", f"not UTF-8 ({e})") from e


def _value(buf: bytes, pos: int, end: int, field: Field, packed: bool) -> tuple[Any, int]:
    """(value of one occurrence of `field` at `pos`, position after it); a list when packed."""
    kind = field.kind
    if kind == "double" or kind == "float":
        codec = _DOUBLE if kind == "double" else _FLOAT
        if not packed:
            if pos + codec.size > end:
                raise WireError("", f"truncated {kind}")
            return codec.unpack_from(buf, pos)[0], pos + codec.size
    elif kind in ("int", "uint", "bool") and not packed:
        value, pos = read_varint(buf, pos, end)
        return _from_varint(kind, value), pos
    size, start = read_varint(buf, pos, end)
    stop = start + size
    if stop > end:
        raise WireError("", f"length {size} runs past the end of its message")
    if isinstance(kind, Message):
        return decode(buf, kind, start, stop), stop
    if packed:
        return _packed(buf, start, stop, kind), stop
    return _bytes_value(buf, start, stop, kind), stop


def decode(buf: bytes, message: Message, start: int = 0, end: int | None = None) -> dict:
    """The fields of `message` in buf[start:end], by name.

    Raises:
      WireError (a ValueError) naming the dotted path of the damaged field.
    """
    end = len(buf) if end is None else end
    out: dict[str, Any] = {name: [] for name in message.repeated}
    by_key = message.by_key
    pos = start
    while pos < end:
        key = buf[pos]
        if key < 0x80:  # one-byte keys: field numbers up to 15, the common case
            pos += 1
        else:
            try:
                key, pos = read_varint(buf, pos, end)
            except WireError as e:
                raise WireError("", f"field key at byte {pos - start}: {e.message}") from None
        entry = by_key.get(key)
        if entry is None:
            try:
                pos = _skip(buf, pos, end, key & 7)
            except WireError as e:
                raise WireError(f"<field {key >> 3}>", e.message) from None
            continue
        field, packed = entry
        try:
            value, pos = _value(buf, pos, end, field, packed)
        except WireError as e:
            index = f"[{len(out[field.name])}]" if field.repeated else ""
            raise e.inside(f"{field.name}{index}") from None
        if not field.repeated:
            out[field.name] = value
        elif packed:
            out[field.name].extend(value)
        else:
            out[field.name].append(value)
    return out
