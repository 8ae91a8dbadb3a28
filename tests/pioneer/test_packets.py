"""ARCOS framing: checksum and command vectors from docs/protocols/pioneer-aria.md, and the incremental parser."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.pioneer.errors import ChecksumError, FramingError
from drivers.pioneer.packets import (Cmd, Packet, PacketParser, build_packet, checksum, command, parse_int_arg,
                                     vel2_split, vel2_value)

VECTORS = [
    ("SYNC0/PULSE", command(Cmd.PULSE), "fa fb 03 00 00 00"),
    ("SYNC1/OPEN", command(Cmd.OPEN), "fa fb 03 01 00 01"),
    ("SYNC2/CLOSE", command(Cmd.CLOSE), "fa fb 03 02 00 02"),
    ("ENABLE 1", command(Cmd.ENABLE, 1), "fa fb 06 04 3b 01 00 05 3b"),
    ("VEL 300", command(Cmd.VEL, 300), "fa fb 06 0b 3b 2c 01 37 3c"),
    ("RVEL -20", command(Cmd.RVEL, -20), "fa fb 06 15 1b 14 00 29 1b"),
    ("ESTOP", command(Cmd.ESTOP), "fa fb 03 37 00 37"),
]


@pytest.mark.parametrize("name,got,want", VECTORS, ids=[v[0] for v in VECTORS])
def test_command_vectors_from_the_protocol_notes(name, got, want):
    assert got == bytes.fromhex(want)


def test_checksum_pairs_big_endian_and_xors_odd_byte():
    assert checksum(bytes.fromhex("043b0100")) == 0x053B
    assert checksum(bytes.fromhex("0b3b2c01")) == 0x373C
    assert checksum(b"\x37") == 0x37
    assert checksum(b"\xff\xff\x00\x02") == 0x0001  # 0xffff + 0x0002 wraps at 16 bits
    assert checksum(b"\x01\x02\x03") == 0x0102 ^ 0x03


def test_negative_arguments_are_sign_magnitude():
    assert command(Cmd.VEL, -300)[4:7] == bytes([0x1B, 0x2C, 0x01])
    assert command(Cmd.VEL, 0)[4:7] == bytes([0x3B, 0, 0])
    for v in (0, 1, -1, 300, -300, 65535, -65535):
        assert parse_int_arg(command(Cmd.VEL, v)[4:-2]) == v
    with pytest.raises(ValueError):
        command(Cmd.VEL, 65536)


def test_string_argument_has_type_and_length():
    assert command(Cmd.PULSE, "ab") == build_packet(0, bytes([0x2B, 2]) + b"ab")


def test_vel2_packs_left_high_right_low():
    # left +10 (200 mm/s), right -5 (-100 mm/s): high byte 0x0A, low byte 0xFB -> 0x0AFB
    assert vel2_value(10, -5) == 0x0AFB
    assert command(Cmd.VEL2, vel2_value(10, -5))[4:7] == bytes([0x3B, 0xFB, 0x0A])
    # left negative: the combined int is negative and goes out sign-magnitude
    assert vel2_value(-1, 1) == -255
    assert command(Cmd.VEL2, vel2_value(-1, 1))[4:7] == bytes([0x1B, 0xFF, 0x00])
    for left in (-128, -1, 0, 1, 127):
        for right in (-128, -1, 0, 1, 127):
            assert vel2_split(vel2_value(left, right)) == (left, right)
    with pytest.raises(ValueError):
        vel2_value(128, 0)


def test_send_size_limit_is_200():
    assert len(build_packet(0x20, bytes(197))) == 3 + 200
    with pytest.raises(ValueError, match="too long"):
        build_packet(0x20, bytes(198))


def test_parser_reads_vectors_split_at_every_byte():
    stream = b"".join(bytes.fromhex(v[2]) for v in VECTORS)
    p = PacketParser()
    got = []
    for b in stream:
        got += p.feed(bytes([b]))
    assert [(g.pid, g.payload) for g in got] == [(v[1][3], v[1][4:-2]) for v in VECTORS]
    assert p.stats.dropped_bytes == 0 and p.pending == 0


def test_parser_drops_bad_checksum_and_resynchronises():
    good = command(Cmd.VEL, 300)
    bad = bytearray(good)
    bad[-1] ^= 0x01
    p = PacketParser()
    got = p.feed(b"\x00\x11garbage" + bytes(bad) + good)
    assert [g.pid for g in got] == [Cmd.VEL]
    assert p.stats.bad_checksum == 1
    assert isinstance(p.errors[-1], ChecksumError)


def test_false_header_in_noise_does_not_swallow_the_next_packet():
    # 0xFA 0xFB 0x40 announces 64 bytes; the real packet sits inside that window.
    good = command(Cmd.ENABLE, 1)
    p = PacketParser()
    got = p.feed(b"\xfa\xfb\x40" + good + bytes(70))
    assert [g.pid for g in got] == [Cmd.ENABLE]
    assert p.stats.bad_checksum == 1


def test_impossible_length_byte_is_a_framing_error():
    p = PacketParser()
    got = p.feed(b"\xfa\xfb\x02\x00" + command(Cmd.OPEN))
    assert [g.pid for g in got] == [Cmd.OPEN]
    assert p.stats.bad_length == 1 and isinstance(p.errors[0], FramingError)


def test_unknown_ids_are_returned_not_errors():
    p = PacketParser()
    got = p.feed(build_packet(0xEE, b"\x01\x02"))
    assert got == [Packet(0xEE, b"\x01\x02", None)]


def test_partial_packet_times_out_between_bytes():
    good = command(Cmd.VEL, 300)
    p = PacketParser(inter_byte_timeout=0.5)
    assert p.feed(good[:5], t=10.0) == []
    got = p.feed(good, t=11.0)  # 1 s later: the stale half is given up, the new packet is read
    assert [g.pid for g in got] == [Cmd.VEL] and got[0].stamp == 11.0
    assert p.stats.timeouts >= 1


def test_stamp_is_the_arrival_of_the_first_byte():
    good = command(Cmd.VEL, 300)
    p = PacketParser(inter_byte_timeout=None)
    assert p.feed(good[:2], t=1.0) == []
    assert p.feed(good[2:5], t=1.2) == []
    (pkt,) = p.feed(good[5:], t=1.4)
    assert pkt.stamp == 1.0


# -- property tests ------------------------------------------------------------------------------------
ids = st.integers(0, 0xF9)  # any ID except 0xFA: a packet must not look like a header start
payload_bytes = st.binary(max_size=60).map(lambda b: b.replace(b"\xfa", b"\xf9"))
packets = st.lists(st.tuples(ids, payload_bytes), min_size=1, max_size=12)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600), st.lists(st.integers(1, 64), max_size=20))
def test_random_bytes_never_raise_and_every_output_is_valid(data, cuts):
    p = PacketParser()
    got, pos = [], 0
    for c in cuts:
        got += p.feed(data[pos:pos + c], t=float(pos))
        pos += c
    got += p.feed(data[pos:], t=float(pos))
    for pkt in got:
        assert build_packet(pkt.pid, pkt.payload, max_n=255)  # re-frames: length and checksum were valid
    s = p.stats
    assert s.bytes_in == len(data)
    assert s.dropped_bytes + p.pending + sum(5 + len(k.payload) for k in got) == len(data)


@settings(max_examples=200, deadline=None)
@given(packets, st.lists(st.binary(min_size=1, max_size=40).map(lambda b: b.replace(b"\xfa", b"\x00")),
                         min_size=1, max_size=12), st.integers(1, 50))
def test_garbage_between_packets_loses_nothing(pkts, garbage, chunk):
    stream = b"".join(garbage[k % len(garbage)] + build_packet(pid, pl) for k, (pid, pl) in enumerate(pkts))
    p = PacketParser()
    got = []
    for i in range(0, len(stream), chunk):
        got += p.feed(stream[i:i + chunk])
    assert [(g.pid, g.payload) for g in got] == pkts


@settings(max_examples=200, deadline=None)
@given(packets, packets, st.data())
def test_recovers_after_corruption(before, after, data):
    head = b"".join(build_packet(pid, pl) for pid, pl in before)
    tail = b"".join(build_packet(pid, pl) for pid, pl in after)
    noise = bytearray(data.draw(st.binary(min_size=1, max_size=80), label="noise"))
    # corrupt: flip bytes of the last 'before' packet, drop some, or insert noise with headers in it
    mode = data.draw(st.sampled_from(["flip", "drop", "insert"]), label="mode")
    last = bytearray(build_packet(*before[-1]))
    head = head[: len(head) - len(last)]
    if mode == "flip":
        k = data.draw(st.integers(0, len(last) - 1))
        last[k] ^= noise[0] or 1
    elif mode == "drop":
        k = data.draw(st.integers(0, len(last) - 1))
        del last[k]
    else:
        last = bytearray(b"\xfa\xfb") + noise + last
    stream = head + bytes(last) + tail
    p = PacketParser(inter_byte_timeout=0.5)
    got = [(g.pid, g.payload) for g in p.feed(stream, t=0.0)]
    # a damaged length byte may announce more bytes than follow: the inter-byte timeout ends the wait
    got += [(g.pid, g.payload) for g in p.feed(b"", t=1.0)]
    assert p.pending == 0
    assert got[: len(before) - 1] == before[:-1]  # everything before the damage
    assert got[-len(after):] == after  # everything after it: the parser re-synchronised
