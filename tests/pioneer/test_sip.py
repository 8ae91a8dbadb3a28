"""Typed decoding of SIP, SYNC2, CONFIG and ENCODER packets."""

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.pioneer.emulator import PioneerEmulator
from drivers.pioneer.errors import DecodeError
from drivers.pioneer.packets import Packet, PacketParser, build_packet
from drivers.pioneer.sip import (SIP_TAIL_FIELDS, ConfigPacket, EncoderPacket, StandardSIP, SyncReply,
                                 UnknownPacket, decode_config, decode_encoder, decode_packet, decode_sip,
                                 decode_sync2, encode_config, encode_encoder, encode_sip, encode_sync2)


def _sip_payload(n_sonar=2, tail=b""):
    fixed = struct.pack("<HHhhhBHhHBB", 0x8123, 0x0010, -1024, 250, -250, 124, 0x0301, 512, 0x0023, 45, n_sonar)
    sonar = b"".join(struct.pack("<BH", i, 1000 + i) for i in range(n_sonar))
    return fixed + sonar + tail


def test_sip_fixed_fields_and_flag_bits():
    sip = decode_sip(0x33, _sip_payload())
    assert sip.moving
    assert (sip.xpos, sip.ypos, sip.thpos) == (0x8123, 0x0010, -1024)
    assert (sip.lvel, sip.rvel, sip.battery, sip.control, sip.compass) == (250, -250, 124, 512, 45)
    assert sip.battery_volts == pytest.approx(12.4)
    # STALL_BUMPERS 0x0301: bit0 left stall, bit8 right stall, bit9 first front bumper
    assert sip.left_stall and sip.right_stall and sip.front_bumpers == 0b1 and sip.rear_bumpers == 0
    # FLAGS 0x23: motors on, sonar array 1, e-stop
    assert sip.motors_enabled and sip.sonar_arrays == 0b0001 and sip.estop
    assert sip.sonar == ((0, 1000), (1, 1001))
    assert all(getattr(sip, f) is None for f in SIP_TAIL_FIELDS) and sip.extra == b""
    assert not decode_sip(0x32, _sip_payload()).moving


@pytest.mark.parametrize("n_tail", range(0, 15))
def test_sip_optional_tail_parsed_by_remaining_length(n_tail):
    full_tail = bytes([1, 2, 3, 4, 5]) + struct.pack("<H", 127) + bytes([2]) + struct.pack("<hH", -150, 0x0102)
    full_tail += b"\xaa\xbb"  # newer firmware fields we do not know: kept raw
    sip = decode_sip(0x32, _sip_payload(tail=full_tail[:n_tail]))
    sizes = [1, 1, 1, 1, 1, 2, 1, 2, 2]
    present = 0
    while present < len(sizes) and sum(sizes[:present + 1]) <= n_tail:
        present += 1
    for k, name in enumerate(SIP_TAIL_FIELDS):
        assert (getattr(sip, name) is not None) == (k < present), name
    assert len(sip.extra) == n_tail - sum(sizes[:present])
    if present == len(sizes):
        assert (sip.battery_x10, sip.charge_state, sip.rotvel, sip.fault_flags) == (127, 2, -150, 0x0102)
        assert sip.battery_volts == pytest.approx(12.7)  # the finer field wins


def test_sip_too_short_is_a_decode_error():
    with pytest.raises(DecodeError, match="too short"):
        decode_sip(0x32, _sip_payload()[:18])
    with pytest.raises(DecodeError, match="sonar"):
        decode_sip(0x32, _sip_payload(n_sonar=2)[:-1])


def test_sip_round_trip():
    sip = StandardSIP(True, 0x7FFF, 3, 2047, -300, 310, 130, 0x0200, -5, 0x07, 1,
                      ((3, 4000), (4, 250)), grip=0, anport=1, analog=2, digin=3, digout=4, battery_x10=131,
                      charge_state=1, rotvel=-55, fault_flags=0)
    pkt = encode_sip(sip)
    assert pkt[3] == 0x33
    (p,) = PacketParser().feed(pkt)
    assert decode_packet(p) == sip


def test_sync2_reply_three_strings():
    raw = build_packet(2, b"Robbie\x00Pioneer\x00p3dx-sh\x00")
    (p,) = PacketParser().feed(raw)
    assert decode_sync2(p.payload) == SyncReply("Robbie", "Pioneer", "p3dx-sh")
    assert encode_sync2(SyncReply("Robbie", "Pioneer", "p3dx-sh")) == raw
    with pytest.raises(DecodeError, match="3 NUL-terminated"):
        decode_sync2(b"Robbie\x00Pioneer")


def test_short_config_ending_at_the_watchdog_still_decodes():
    cfg = ConfigPacket("Pioneer", "p3dx-sh", "SN42", 0, 500, 2200, 300, 2000, 1000, "Robbie", 100, 0, 0, 0, 1, 1,
                       110, 16570, 2000)
    (p,) = PacketParser().feed(encode_config(cfg))
    got = decode_packet(p)
    assert p.pid == 0x20 and got == cfg
    assert got.transvel_max is None and got.extra == b""
    with pytest.raises(DecodeError, match="watchdog"):
        decode_config(p.payload[:-1])


def test_full_config_fields_sit_where_aria_reads_them():
    """Hand-packed in the reference client's order: the current limits follow the watchdog, NormalMPacs and
    four u16 (stall value/count, joystick speeds); ResetBaud is the fifth u8 after the sixteen u16 of
    limits, accelerations and PID gains."""
    head = b"Pioneer\x00p3dx-sh\x00SN42\x00" + struct.pack("<B5H", 0, 500, 2200, 300, 2000, 1000) + b"Robbie\x00"
    head += struct.pack("<3B2HB3H", 100, 0, 0, 0, 1, 1, 110, 16570, 2000)
    body = struct.pack("<B4H", 0, 255, 10, 300, 50)
    body += struct.pack("<12H", 300, 1500, 200, 200, 40, 20, 0, 300, 300, 40, 30, 0)
    body += struct.pack("<6B", 5, 5, 0, 40, 2, 0) + struct.pack("<hBBHH", -3, 0, 0, 128, 105) + b"fw 1\x00"
    body += struct.pack("<HHB6HBHb", 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, -5)
    body += struct.pack("<HBHH", 0, 0, 0, 0) + b"boot\x00" + struct.pack("<Ih", 7, -1)
    cfg = decode_config(head + body)
    assert (cfg.watchdog, cfg.normal_mpacs, cfg.stall_val, cfg.joy_rotvel) == (2000, 0, 255, 50)
    assert (cfg.rotvel_max, cfg.transvel_max, cfg.rot_accel, cfg.trans_accel, cfg.trans_ki) == (300, 1500, 200, 300, 0)
    assert (cfg.front_bumps, cfg.sonar_cycle, cfg.reset_baud, cfg.drift_factor, cfg.ticks_mm) == (5, 40, 2, -3, 128)
    assert cfg.firmware_version == "fw 1" and cfg.high_temperature_shutdown == -5
    assert (cfg.bootloader_version, cfg.config_flags, cfg.gyro_fw_version, cfg.extra) == ("boot", 7, -1, b"")
    (p,) = PacketParser().feed(encode_config(cfg))
    assert p.payload == head + body and decode_packet(p) == cfg


def test_config_stopping_mid_way_leaves_the_rest_unset():
    cfg = PioneerEmulator().config_packet()
    (p,) = PacketParser().feed(encode_config(cfg))
    cut = decode_config(p.payload[:-20])
    assert cut.transvel_max == 1500 and cut.bootloader_version is None and cut.gyro_fw_version is None


def test_encoder_packet():
    (p,) = PacketParser().feed(encode_encoder(EncoderPacket(-5, 1 << 20)))
    assert decode_packet(p) == EncoderPacket(-5, 1 << 20)
    with pytest.raises(DecodeError):
        decode_encoder(b"\x00" * 7)


def test_unknown_ids_are_skipped_not_errors():
    assert decode_packet(Packet(0xF0, b"\x01")) == UnknownPacket(0xF0, b"\x01")


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([0x32, 0x33, 0x20, 0x90, 0x98, 0xF0]), st.binary(max_size=120))
def test_random_payloads_raise_only_decode_error(pid, payload):
    try:
        decode_packet(Packet(pid, payload))
    except DecodeError:
        pass
