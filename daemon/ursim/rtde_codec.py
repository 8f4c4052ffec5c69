"""The RTDE wire format (public, Universal Robots RTDE guide): package headers, variable types and their encoding.

Every package is `>HB` (total size in bytes including the 3-byte header, package type) followed by its payload,
big-endian throughout. This module knows only bytes and Python values; `rtde_server` gives them meaning.
"""

from __future__ import annotations

import struct

HEADER = struct.Struct(">HB")

# Package types (ASCII letters on the wire).
REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

# RTDE type name -> struct format of one value (vectors are tuples).
TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}


def pack(kind: int, payload: bytes = b"") -> bytes:
    """One package: header + payload."""
    size = HEADER.size + len(payload)
    if size > 0xFFFF:
        raise ValueError(f"RTDE package of {size} bytes exceeds the 65535-byte limit")
    return HEADER.pack(size, kind) + payload


def split(buffer: bytearray) -> list[tuple[int, bytes]]:
    """Remove every complete package from the front of `buffer`; returns [(type, payload)], leaves partial data."""
    out = []
    while len(buffer) >= HEADER.size:
        size, kind = HEADER.unpack_from(buffer)
        if size < HEADER.size:
            raise ValueError(f"RTDE header announces {size} bytes, less than the header itself")
        if len(buffer) < size:
            break
        out.append((kind, bytes(buffer[HEADER.size : size])))
        del buffer[:size]
    return out


def recipe_struct(types: list[str]) -> struct.Struct:
    """Struct for the concatenated values of a recipe (without the leading recipe id byte)."""
    return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in types))


def encode_values(types: list[str], values: list) -> bytes:
    """Flatten values (scalars, or sequences for vector types) in recipe order and pack them."""
    flat: list = []
    for t, v in zip(types, values, strict=True):
        if t.startswith("VECTOR"):
            flat.extend(v)
        else:
            flat.append(v)
    return recipe_struct(types).pack(*flat)


def decode_values(types: list[str], data: bytes) -> list:
    """Inverse of encode_values: a list with one entry per variable (tuples for vectors)."""
    flat = list(recipe_struct(types).unpack(data))
    out: list = []
    for t in types:
        n = len(TYPE_FORMATS[t]) > 1 and int(TYPE_FORMATS[t][0]) or 1
        out.append(tuple(flat[:n]) if n > 1 else flat[0])
        del flat[:n]
    return out


def text_message(message: str, source: str = "ursim", level: int = 1) -> bytes:
    """A protocol-2 text message package (level 0 exception, 1 error, 2 warning, 3 info)."""
    m, s = message.encode()[:255], source.encode()[:255]
    return pack(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))
