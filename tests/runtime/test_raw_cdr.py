"""The direct RawBytes decoder agrees with rosbags' deserialiser on every message and declines what it cannot
vouch for."""

from __future__ import annotations

import math
import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.serde import SerdeError

from runtime import messages as M
from runtime.raw_cdr import raw_bytes_fields

TS = M.typestore()


def _serialise(sec: int, nanosec: int, frame_id: str, direction: str, host_time: float, url: str,
               data: bytes) -> bytes:
    T = TS.types
    msg = T[M.RAW_BYTES_TYPE](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
        sec=sec, nanosec=nanosec), frame_id=frame_id), direction=direction, host_time=host_time, url=url,
        data=np.frombuffer(data, dtype=np.uint8).copy())
    return bytes(TS.serialize_cdr(msg, M.RAW_BYTES_TYPE))


def _rosbags(raw: bytes):
    msg = TS.deserialize_cdr(raw, M.RAW_BYTES_TYPE)
    return msg.header.frame_id, msg.host_time, msg.direction, msg.url, bytes(msg.data)


def _same(a, b) -> bool:
    """Field by field; host_time bit for bit (NaN included)."""
    return (a[0], a[2], a[3], a[4]) == (b[0], b[2], b[3], b[4]) and \
        struct.pack("<d", a[1]) == struct.pack("<d", b[1])


text = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=12)
messages = st.builds(_serialise, st.integers(-2**31, 2**31 - 1), st.integers(0, 2**32 - 1), text,
                     text, st.floats(allow_nan=True, allow_infinity=True), text, st.binary(max_size=64))


@settings(max_examples=300, deadline=None)
@given(messages)
def test_decodes_every_message_as_rosbags(raw):
    got = raw_bytes_fields(raw)
    assert got is not None and _same(got, _rosbags(raw))
    assert type(got[4]) is bytes


@settings(max_examples=400, deadline=None)
@given(messages, st.data())
def test_damaged_bytes_decode_as_rosbags_or_not_at_all(raw, data):
    """Cut short, lengthened or with one byte changed: either rosbags decodes the same thing or this decoder
    declines (and rosbags, asked instead, gives its own answer)."""
    how = data.draw(st.sampled_from(["cut", "grow", "flip"]))
    if how == "cut":
        bad = raw[:data.draw(st.integers(0, len(raw) - 1))]
    elif how == "grow":
        bad = raw + data.draw(st.binary(min_size=1, max_size=8))
    else:
        i = data.draw(st.integers(0, len(raw) - 1))
        bad = raw[:i] + bytes([data.draw(st.integers(0, 255))]) + raw[i + 1:]
    got = raw_bytes_fields(bad)
    try:
        want = _rosbags(bad)
    except SerdeError:
        assert got is None
    else:
        assert got is None or _same(got, want)


def test_declines_big_endian_cdr_which_rosbags_decodes():
    T = TS.types
    msg = T[M.RAW_BYTES_TYPE](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
        sec=1, nanosec=2), frame_id="base"), direction="tx", host_time=math.pi, url="serial:///dev/ttyS0",
        data=np.frombuffer(b"\xfa\xfb\x03\x01\x00\x01", dtype=np.uint8).copy())
    big = bytes(TS.serialize_cdr(msg, M.RAW_BYTES_TYPE, little_endian=False))
    assert raw_bytes_fields(big) is None
    assert _rosbags(big) == ("base", math.pi, "tx", "serial:///dev/ttyS0", b"\xfa\xfb\x03\x01\x00\x01")


def test_a_recorded_message():
    raw = bytes(TS.serialize_cdr(M.raw_bytes_msg(1_700_000_000_123_456_789, "laser", "rx", 1234.5678,
                                                 b"MD0000108001101\n", "tcp://192.168.0.10:10940"), M.RAW_BYTES_TYPE))
    assert raw_bytes_fields(raw) == ("laser", 1234.5678, "rx", "tcp://192.168.0.10:10940", b"MD0000108001101\n")
