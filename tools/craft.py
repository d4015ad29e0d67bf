"""Crafting .stg and decoder bytes for hostile-input tests (tools/make_malicious_files.py, tools/fuzz.py):
take a file apart, edit it, and seal it again with a valid checksum, so that a reader's deeper checks
are reached. Not a reader or a writer of the format: stg_runtime.format is."""
from __future__ import annotations

import hashlib
import json
import struct

PREFIX = struct.Struct("<8sHHQ")  # magic, major, minor, header length (formats/stg-v1.md, section 4)


def split(data: bytes) -> tuple[dict, bytes, tuple[int, int]]:
    """(header, data section, (major, minor)) of a well-formed file."""
    _, major, minor, length = PREFIX.unpack_from(data)
    return json.loads(data[PREFIX.size:PREFIX.size + length]), data[PREFIX.size + length:-32], (major, minor)


def seal(header, section: bytes, version=(1, 0), magic: bytes = b"\x89STG\r\n\x1a\n") -> bytes:
    """A file of `header` (a dict, or the header's bytes as they are) and `section`, with its checksum."""
    text = json.dumps(header).encode() if isinstance(header, dict) else header
    body = PREFIX.pack(magic, *version, len(text)) + text + section
    return body + hashlib.sha256(body).digest()


def varint(value: int) -> bytes:
    """A protobuf varint (any non-negative int, also beyond 64 bits)."""
    out = bytearray()
    while value >= 0x80:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    return bytes(out + bytes([value]))


def field(number: int, wire: int, payload: bytes, key_bits: int = 0) -> bytes:
    """A protobuf field: key (with extra high bits `key_bits` set, for keys beyond 32 bits) and payload
    (length-prefixed for wire type 2)."""
    key = varint((number << 3 | wire) | key_bits)
    return key + (varint(len(payload)) + payload if wire == 2 else payload)
