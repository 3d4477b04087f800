"""The MCAP file format's constants and primitive fields, for the writer and the reader.

A record is (opcode u8, content length u64, content); integers are
little-endian, strings and byte arrays are prefixed by their u32 length, a
string map by its u32 byte length. https://mcap.dev/spec
"""
from __future__ import annotations

import struct
from enum import IntEnum

MAGIC = b"\x89MCAP0\r\n"
#: Footer record: opcode, length 20, summary start, summary offset start, summary CRC [bytes].
FOOTER_BYTES = 29
#: A Message record's head: opcode, length, channel, sequence, log and publish time [bytes].
MESSAGE_HEAD = 31


class Op(IntEnum):
    """Record opcodes."""

    HEADER = 0x01
    FOOTER = 0x02
    SCHEMA = 0x03
    CHANNEL = 0x04
    MESSAGE = 0x05
    CHUNK = 0x06
    MESSAGE_INDEX = 0x07
    CHUNK_INDEX = 0x08
    STATISTICS = 0x0B
    METADATA = 0x0C
    METADATA_INDEX = 0x0D
    SUMMARY_OFFSET = 0x0E
    DATA_END = 0x0F


def encode_string(value: str | bytes) -> bytes:
    """A string (or byte array) field: u32 length, then the bytes."""
    data = value.encode() if isinstance(value, str) else value
    return struct.pack("<I", len(data)) + data


def encode_string_map(values: dict[str, str]) -> bytes:
    """A map<string, string> field: u32 byte length, then key, value, ..."""
    return encode_string(b"".join(encode_string(k) + encode_string(v) for k, v in values.items()))


def decode_string(buf, pos: int) -> tuple[str, int]:
    """The string field at ``pos`` and the position after it."""
    n = struct.unpack_from("<I", buf, pos)[0]
    return bytes(buf[pos + 4:pos + 4 + n]).decode(), pos + 4 + n


def decode_string_map(buf, pos: int) -> tuple[dict[str, str], int]:
    """The map<string, string> field at ``pos`` and the position after it."""
    n = struct.unpack_from("<I", buf, pos)[0]
    end, pos, out = pos + 4 + n, pos + 4, {}
    while pos < end:
        k, pos = decode_string(buf, pos)
        v, pos = decode_string(buf, pos)
        out[k] = v
    return out, end
