"""A direct decoder of the CDR form of ``glassmap_msgs/msg/RawBytes`` (see :data:`runtime.messages.RAW_BYTES_MSG`).

:func:`raw_bytes_fields` reads the fields the raw replay needs with ``struct`` from the little-endian CDR
the recorder writes, without building the message object the rosbags type store would. It decodes only
what rosbags' ``deserialize_cdr`` decodes, to the same values; for anything else (big-endian CDR, a bad
length, a missing string terminator, invalid UTF-8, trailing bytes) it returns None, and the caller hands
the bytes to rosbags, which decodes them or raises its own error.

Layout (offsets after the 4-byte encapsulation header, each field aligned to its size): header.stamp
(int32 sec, uint32 nanosec), header.frame_id (string), direction (string), host_time (float64), url
(string), data (uint8 sequence). A string is a uint32 length counting a NUL terminator, then the bytes.
"""

from __future__ import annotations

import struct

_U32 = struct.Struct("<I")
_F64 = struct.Struct("<d")
_LITTLE_ENDIAN_CDR = b"\x00\x01"
_BASE = 4  # CDR alignment counts from the end of the encapsulation header
MAX_SEQUENCE = 2**32 - 1  # rosbags' default max_sequence_length


class _NotPlain(Exception):
    """The bytes are not plain little-endian CDR of the type (rosbags decides what they are)."""


def _align(pos: int, size: int) -> int:
    return ((pos - _BASE + size - 1) & -size) + _BASE


def _string(data: bytes, pos: int) -> tuple[str, int]:
    pos = _align(pos, 4)
    size = _U32.unpack_from(data, pos)[0]
    end = pos + 4 + size
    if size < 1 or end > len(data) or data[end - 1] != 0:
        raise _NotPlain
    return str(data[pos + 4:end - 1], "utf-8"), end


def raw_bytes_fields(data: bytes, max_sequence: int = MAX_SEQUENCE) -> tuple[str, float, str, str, bytes] | None:
    """(header.frame_id, host_time (s), direction, url, data) of a serialised RawBytes message, or None if
    the bytes are not plain little-endian CDR this decoder vouches for (then use rosbags' deserialiser)."""
    if data[:2] != _LITTLE_ENDIAN_CDR or len(data) < _BASE:
        return None
    try:
        frame_id, pos = _string(data, _BASE + 8)  # after header.stamp (int32 sec, uint32 nanosec)
        direction, pos = _string(data, pos)
        pos = _align(pos, 8)
        host_time = _F64.unpack_from(data, pos)[0]
        url, pos = _string(data, pos + 8)
        pos = _align(pos, 4)
        size = _U32.unpack_from(data, pos)[0]
        pos += 4
        if pos + size > len(data) or size > max_sequence:
            return None
        payload = data[pos:pos + size]
    except (_NotPlain, struct.error, UnicodeDecodeError):
        return None
    if pos + size + 3 < len(data):  # more than CDR's trailing padding: rosbags rejects the size
        return None
    return frame_id, host_time, direction, url, payload
