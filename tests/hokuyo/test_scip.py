"""SCIP codec: spec vectors, decoding of every scan command, corrupt input, and property tests."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.hokuyo.errors import (
    AbnormalState,
    BadValue,
    ChecksumError,
    CommandRejected,
    Denied,
    GarbageData,
    ScipProtocolError,
    TruncatedMessage,
    UndefinedCommand,
    Unstable,
    status_error,
)
from drivers.hokuyo.scip import (
    LINE_PAYLOAD,
    InfoReply,
    Reply,
    ScanReply,
    ScipParser,
    TimeReply,
    checksum,
    data_lines,
    decode_scan_data,
    decode_values,
    distances_to_metres,
    encode_command,
    encode_int,
    encode_reply,
    encode_scan_payload,
    encode_values,
    further_echoes,
    scan_params,
)
from tests.hokuyo.vectors import PP_REPLY



def feed_all(data: bytes, chunks=None) -> list:
    p = ScipParser()
    if chunks is None:
        return p.feed(data)
    out, k = [], 0
    for n in chunks:
        out += p.feed(data[k:k + n])
        k += n
    return out + p.feed(data[k:])


def me_message(d, i, ts=123456, echo=b"ME0000108001000", status="99"):
    return encode_reply(echo, status, encode_scan_payload("ME", ts, d, i))


# ------------------------------------------------------------------------------------------ spec vectors
def test_checksum_and_value_vectors():
    assert chr(checksum(b"Hokuyo")) == "o"
    assert encode_int(1234, 2) == b"CB" and encode_int(5432, 3) == b"1Dh" and encode_int(16000000, 4) == b"m2@0"
    assert decode_values(b"CB", 2).tolist() == [1234]
    assert decode_values(b"1Dh" + b"CB0", 3).tolist() == [5432, encode_values_back(b"CB0")]
    assert decode_values(b"m2@0", 4).tolist() == [16000000]
    assert decode_values(b"000", 3).tolist() == [0] and decode_values(b"ooo", 3).tolist() == [(1 << 18) - 1]
    with pytest.raises(ValueError):
        encode_int(1 << 12, 2)


def encode_values_back(chars: bytes) -> int:
    v = 0
    for c in chars:
        v = (v << 6) | (c - 0x30)
    return v


def test_real_pp_reply_and_status_line():
    (r,) = feed_all(PP_REPLY)
    assert isinstance(r, InfoReply) and r.status == "00"
    assert r.fields == {"MODL": "UTM-30LX-EW", "DMIN": "23", "DMAX": "60000", "ARES": "1440", "AMIN": "0",
                        "AMAX": "1080", "AFRT": "540", "SCAN": "2400"}


def test_info_values_may_hold_semicolons_and_colons():
    # II TIME is 4 encoded chars on the UTM, which can be ':' or ';'; the checksum may itself be ';'.
    body_lines = b""
    for key, value in (("TIME", ":;0;"), ("STAT", "a:b;c"), ("X", "1")):
        body = f"{key}:{value}".encode()
        body_lines += body + b";" + bytes([checksum(body)]) + b"\n"
    (r,) = feed_all(b"II\n00P\n" + body_lines + b"\n")
    assert r.fields == {"TIME": ":;0;", "STAT": "a:b;c", "X": "1"}


def test_status_codes_become_specific_errors_with_code_and_command():
    cases = {"0E": UndefinedCommand, "0L": AbnormalState, "0M": Unstable, "10": Denied, "04": CommandRejected}
    for code, cls in cases.items():
        err = status_error(code, "GD0000108000")
        assert isinstance(err, cls) and err.code == code and err.command == "GD0000108000"
    (r,) = feed_all(b"%ST\n0E" + bytes([checksum(b"0E")]) + b"\n\n")
    assert r.command == "%ST" and r.status == "0E"
    with pytest.raises(UndefinedCommand) as info:
        r.raise_for_status()
    assert info.value.code == "0E" and info.value.command == "%ST"


def test_command_encoding():
    assert encode_command("ME", scan_params(0, 1080, 1, 0, 0)) == b"ME0000108001000\n"
    assert encode_command("GD", scan_params(44, 725, 1)) == b"GD0044072501\n"
    assert encode_command("TM", "1") == b"TM1\n"
    assert encode_command("VV", string="id 1") == b"VV;id 1\n"
    assert encode_command("%ST") == b"%ST\n"
    for bad in (dict(command="me"), dict(command="ME", params="1a"), dict(command="VV", string="x" * 17),
                dict(command="VV", string="a;b")):
        with pytest.raises(ValueError):
            encode_command(**bad)
    with pytest.raises(ValueError):
        scan_params(10, 5)


# ------------------------------------------------------------------------------------------ scan decoding
def test_me_scan_with_values_straddling_lines():
    rng = np.random.default_rng(1)
    d, i = rng.integers(0, 60001, 1081), rng.integers(0, 1 << 18, 1081)
    msg = me_message(d, i)
    lines = msg.split(b"\n")
    assert len(lines[3]) == 65 and (1081 * 6) % 64 != 0  # 64 payload chars: 6-char records straddle lines
    (r,) = feed_all(msg)
    assert isinstance(r, ScanReply) and r.status == "99" and r.timestamp_ms == 123456
    assert np.array_equal(r.distances, d) and np.array_equal(r.intensities, i)
    assert (r.start, r.end, r.cluster, r.skip, r.remaining) == (0, 1080, 1, 0, 0)


@pytest.mark.parametrize("cmd,width", [("MD", 3), ("MS", 2), ("GD", 3), ("GS", 2)])
def test_distance_only_commands(cmd, width):
    d = (np.arange(200) * 97) % (4096 if width == 2 else 60001)
    params = "0100029901" + ("000" if cmd[0] == "M" else "")
    status = "99" if cmd[0] == "M" else "00"
    (r,) = feed_all(encode_reply((cmd + params).encode(), status, encode_scan_payload(cmd, 7, d)))
    assert np.array_equal(r.distances, d) and r.intensities is None and r.timestamp_ms == 7


@pytest.mark.parametrize("cmd", ["ND", "NE", "HD", "HE"])
def test_multi_echo_with_ampersands(cmd):
    n = 300
    m = np.full((n, 3), -1)
    m[:, 0] = np.arange(n) * 10 + 100
    m[::2, 1] = 5000
    m[::4, 2] = 7000
    inten = np.where(m >= 0, 3000, -1) if cmd[1] == "E" else None
    params = "0000029901" + ("000" if cmd[0] == "N" else "")
    msg = encode_reply((cmd + params).encode(), "99" if cmd[0] == "N" else "00",
                       encode_scan_payload(cmd, 9, m, inten))
    assert b"&" in msg
    (r,) = feed_all(msg)
    assert np.array_equal(r.multi, m) and np.array_equal(r.distances, m[:, 0])
    if inten is not None:
        assert np.array_equal(r.multi_intensities, inten)


def test_ampersand_as_last_character_of_a_line():
    # ND: steps of 3 chars; 21 steps = 63 chars, then '&' is the 64th char of the first data line.
    m = np.full((30, 3), -1)
    m[:, 0] = 1000
    m[20, 1] = 2000
    payload = encode_scan_payload("ND", 0, m)
    first_data = payload.split(b"\n")[1]
    assert first_data[63:64] == b"&"
    (r,) = feed_all(encode_reply(b"ND0000002901000", "99", payload))
    assert np.array_equal(r.multi, m)


@pytest.mark.parametrize("data, why", [
    (b"&000000", "'&' not followed by an echo"),  # before the first echo
    (b"000000&&000000", "'&' not followed by an echo"),
    (b"000&000000000", "'&' not followed by an echo"),  # inside an echo
    (b"000000&", "'&' not followed by an echo"),
    (b"000000&000000&000000&000000", "more than 3 echoes"),
    (b"000000&00000", "not whole echoes"),
    (b"000\x7f00", "outside the SCIP 6-bit alphabet"),
    (b"000/00", "outside the SCIP 6-bit alphabet"),
])
def test_malformed_multi_echo_data_is_refused_with_the_reason(data, why):
    # well-formed data take a compiled fast path; anything else must still say what is wrong
    with pytest.raises(BadValue, match=why):
        decode_scan_data("NE", data)
    good = encode_values(np.array([1000, 50]), 3) + b"&" + encode_values(np.array([2000, 60, 3000, 70]), 3)
    _, _, multi, mint = decode_scan_data("NE", good)
    assert multi.tolist() == [[1000, 2000, -1], [3000, -1, -1]] and mint.tolist() == [[50, 60, -1], [70, -1, -1]]


def test_error_codes_map_to_nan_and_inf():
    mm = np.array([0, 1, 2, 3, 22, 23, 1234, 60000, 60001, -1])
    r = distances_to_metres(mm, dmin=23, dmax=60000)
    assert np.isnan(r[[0, 2, 3, 4, 9]]).all()
    assert np.isinf(r[[1, 8]]).all() and (r[[1, 8]] > 0).all()
    assert r[5] == pytest.approx(0.023) and r[6] == pytest.approx(1.234) and r[7] == pytest.approx(60.0)


def test_compiled_conversion_equals_the_numpy_one_to_the_bit():
    """Integer millimetres go through the compiled loop (drivers/hokuyo/scip_jit.py); floats through numpy."""
    rng = np.random.default_rng(5)
    mm = rng.integers(-1, 70000, (1081, 3)).astype(np.int32)
    mm[rng.random(mm.shape) < 0.05] = 1
    for a in (mm[:, 0], mm[:, 1:], mm, np.zeros((0, 2), np.int32)):
        got = distances_to_metres(a, 23, 60000)
        want = distances_to_metres(a.astype(np.float64), 23, 60000)
        assert got.shape == a.shape and got.dtype == np.float64
        np.testing.assert_array_equal(got, want)



def test_further_echoes_compiled_equal_the_numpy_ones_to_the_bit():
    """The echoes after the first (drivers/hokuyo/scip_jit.py) as the column slice through numpy gives them:
    metres as distances_to_metres, intensities NaN where the echo is absent."""
    rng = np.random.default_rng(6)
    mm = rng.integers(-1, 70000, (1081, 3)).astype(np.int32)
    mm[rng.random(mm.shape) < 0.3] = -1
    mm[rng.random(mm.shape) < 0.05] = 1
    inten = rng.integers(0, 2**20, mm.shape).astype(np.int32)
    for m, i in ((mm, inten), (mm, None), (mm[:, :2], inten[:, :2]), (mm[:, :1], inten[:, :1]),
                 (np.zeros((0, 3), np.int32), np.zeros((0, 3), np.int32)), (mm.astype(np.float64), inten)):
        echoes, echo_int = further_echoes(m, i, 23, 60000)
        want = distances_to_metres(m[:, 1:].astype(np.float64), 23, 60000)
        assert echoes.shape == want.shape and echoes.dtype == np.float64 and echoes.flags.c_contiguous
        np.testing.assert_array_equal(echoes, want)
        if i is None:
            assert echo_int is None
        else:
            want_i = np.where(m[:, 1:] >= 0, i[:, 1:], np.nan)
            assert echo_int.shape == want_i.shape and echo_int.dtype == np.float64
            assert echo_int.tobytes() == want_i.tobytes()  # NaN bits included

def test_time_reply_and_plain_replies():
    ts = encode_values(np.array([16000000]), 4)
    out = feed_all(b"TM1\n00P\n" + data_lines(ts) + b"\n" + b"BM\n02R\n\n" + b"QT\n00P\n\n")
    assert isinstance(out[0], TimeReply) and out[0].time_ms == 16000000
    assert [type(x) for x in out[1:]] == [Reply, Reply] and out[1].status == "02"


def test_stream_ack_then_scans_in_one_chunk_and_byte_by_byte():
    d = np.full(1081, 1500)
    data = b"ME0000108001000\n00P\n\n" + me_message(d, d, ts=1) + me_message(d, d, ts=26)
    for chunks in (None, [1] * len(data), [7, 500, 3, 64]):
        out = feed_all(data, chunks)
        assert [type(x) for x in out] == [Reply, ScanReply, ScanReply]
        assert [x.timestamp_ms for x in out[1:]] == [1, 26]


# ------------------------------------------------------------------------------------------- bad input
def test_bad_checksum_is_reported_and_next_message_survives():
    d = np.full(1081, 1500)
    bad = bytearray(me_message(d, d))
    bad[200] = ord("0") if bad[200] != ord("0") else ord("1")
    out = feed_all(bytes(bad) + me_message(d, d, ts=2))
    assert isinstance(out[0], ChecksumError) and out[0].command == "ME"
    assert isinstance(out[1], ScanReply) and out[1].timestamp_ms == 2


def test_lost_terminator_truncation_and_garbage():
    d = np.full(1081, 1500)
    good = me_message(d, d, ts=5)
    truncated = good[:3000] + b"\n"  # cut inside a line, no blank line: the next message starts inside it
    out = feed_all(b"\x00noise\xff\n" + truncated + good + b"zz%" + good)
    kinds = [type(x) for x in out]
    assert kinds == [GarbageData, TruncatedMessage, ScanReply, GarbageData, ScanReply]
    assert out[0].nbytes == 8 and out[3].nbytes == 3


def test_unexpected_echo_and_short_scan_are_reported():
    d = np.full(100, 1500)
    wrong_len = encode_reply(b"ME0000108001000", "99", encode_scan_payload("ME", 1, d, d))
    out = feed_all(wrong_len)
    assert isinstance(out[0], TruncatedMessage) and "expected" in str(out[0])


def test_memory_stays_bounded_without_line_ends():
    p = ScipParser()
    out = []
    for _ in range(100):
        out += p.feed(b"x" * 10000)
    assert p.buffered < 20000
    assert sum(x.nbytes for x in out if isinstance(x, GarbageData)) >= 900000


# --------------------------------------------------------------------------------------------- properties
@st.composite
def scan_messages(draw):
    cmd = draw(st.sampled_from(["MD", "MS", "ME", "ND", "NE", "GD", "GE", "HE"]))
    start = draw(st.integers(0, 1080))
    end = draw(st.integers(start, min(start + 300, 1080)))
    cluster = draw(st.integers(0, 5))
    n = (end - start) // max(cluster, 1) + 1
    hi = 4095 if cmd[1] == "S" else 60000
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    ts = draw(st.integers(0, (1 << 24) - 1))
    if cmd[0] in "NH":
        echoes = rng.integers(1, 4, n)
        d = np.where(np.arange(3)[None, :] < echoes[:, None], rng.integers(0, hi, (n, 3)), -1)
        i = np.where(d >= 0, rng.integers(0, 1 << 18, (n, 3)), -1)
    else:
        d, i = rng.integers(0, hi + 1, n), rng.integers(0, 1 << 18, n)
    params = scan_params(start, end, cluster, *( (draw(st.integers(0, 9)), draw(st.integers(0, 99)))
                                                 if cmd[0] in "MN" else (None, None)))
    status = "99" if cmd[0] in "MN" else "00"
    msg = encode_reply((cmd + params).encode(), status,
                       encode_scan_payload(cmd, ts, d, i if cmd[1] == "E" else None))
    return msg, cmd, ts, d, (i if cmd[1] == "E" else None)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scan_messages(), st.lists(st.integers(1, 400), max_size=20))
def test_encode_decode_round_trip_in_any_chunking(case, chunks):
    msg, cmd, ts, d, i = case
    (r,) = feed_all(msg, chunks)
    assert isinstance(r, ScanReply) and r.command == cmd and r.timestamp_ms == ts
    if cmd[0] in "NH":
        assert np.array_equal(r.multi, d)
        if i is not None:
            assert np.array_equal(r.multi_intensities, i)
    else:
        assert np.array_equal(r.distances, d)
        if i is not None:
            assert np.array_equal(r.intensities, i)


@st.composite
def corruptions(draw, n):
    kind = draw(st.sampled_from(["flip", "insert", "delete", "cut"]))
    pos = draw(st.integers(0, n - 1))
    junk = draw(st.binary(min_size=1, max_size=30))
    return kind, pos, junk


def corrupt(stream: bytearray, kind: str, pos: int, junk: bytes) -> None:
    """Flip a byte, insert or delete bytes, or cut the stream short at ``pos`` (in place)."""
    if kind == "flip":
        stream[pos] ^= junk[0] or 1
    elif kind == "insert":
        stream[pos:pos] = junk
    elif kind == "delete":
        del stream[pos:pos + len(junk)]
    else:
        del stream[pos:]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(scan_messages(), min_size=1, max_size=3), st.data(), st.lists(st.integers(1, 300), max_size=10))
def test_random_corruption_never_escapes_and_always_resynchronises(cases, data, chunks):
    stream = bytearray(b"".join(c[0] for c in cases))
    for _ in range(data.draw(st.integers(1, 4))):
        if not stream:
            break
        corrupt(stream, *data.draw(corruptions(len(stream))))
    sentinel = me_message(np.full(1081, 4321), np.full(1081, 99), ts=777)
    out = feed_all(bytes(stream) + sentinel, chunks)  # must not raise
    assert all(isinstance(x, (Reply, ScipProtocolError)) for x in out)
    last = out[-1]
    assert isinstance(last, ScanReply) and last.timestamp_ms == 777 and (last.distances == 4321).all()


@pytest.mark.parametrize("chunk", [None, 7, 64])
def test_cut_message_glued_to_next_echo_in_a_line_with_a_passing_checksum_resynchronises(chunk):
    """A message cut inside a data line, glued to the next echo so the line is 64 chars + a checksum char
    that happens to be right: the next message is still found (a hypothesis example, kept)."""
    a = me_message(np.full(1081, 1000), np.full(1081, 5), ts=1)
    echo = b"ME0000108001000"
    cut = a.index(b"\n", 200) + 1  # the start of a full data line
    part = bytearray(a[cut:cut + 65 - len(echo)])
    head = bytes(part[1:]) + echo[:-1]  # the line's first 64 chars but the one to adjust
    part[0] = next(c for c in range(0x30, 0x70) if checksum(bytes([c]) + head) == echo[-1])
    sentinel = me_message(np.full(1081, 4321), np.full(1081, 99), ts=777, echo=echo)
    stream = a[:cut] + bytes(part) + sentinel
    line = stream[cut:stream.index(b"\n", cut)]
    assert len(line) == 65 and line[-1] == checksum(line[:64])  # the glued line passes as a data line
    out = feed_all(stream, None if chunk is None else [chunk] * (len(stream) // chunk + 1))
    assert isinstance(out[0], TruncatedMessage)
    last = out[-1]
    assert isinstance(last, ScanReply) and last.timestamp_ms == 777 and (last.distances == 4321).all()


def _summary(items):
    garbage = sum(x.nbytes for x in items if isinstance(x, GarbageData))
    rest = []
    for x in items:
        if isinstance(x, ScanReply):
            rest.append(("scan", x.command, x.timestamp_ms, x.distances.tobytes()))
        elif not isinstance(x, GarbageData):
            rest.append((type(x).__name__, getattr(x, "status", "")))
    return garbage, rest


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(scan_messages(), min_size=1, max_size=3), st.data())
def test_whole_messages_and_single_bytes_decode_alike(cases, data):
    """The fast path (whole messages in one read) and the line state machine agree, also on bad input."""
    stream = bytearray(b"".join(c[0] for c in cases))
    kind, pos, junk = data.draw(corruptions(len(stream)))
    corrupt(stream, "delete" if kind == "cut" else kind, pos, junk)
    stream += cases[0][0]
    whole = feed_all(bytes(stream))
    single = feed_all(bytes(stream), [1] * len(stream))
    assert _summary(whole) == _summary(single)


@pytest.mark.parametrize("next_echo", [b"MS0540054001000", b"VV", b"TM0"])
def test_partial_echo_without_line_end_resynchronises_at_the_next_echo(next_echo):
    """A link cut mid-echo leaves ``MS0540054001000;`` with no LF: the next reply's echo must not be read
    as its string field."""
    p = ScipParser()
    assert p.feed(b"MS0540054001000;") == []
    if next_echo.startswith(b"MS"):
        reply = encode_reply(next_echo, "99", encode_scan_payload("MS", 1234, np.arange(100, 101)))
    else:
        reply = encode_reply(next_echo, "00")
    out = p.feed(reply)
    assert isinstance(out[0], GarbageData) and out[0].nbytes == len(b"MS0540054001000;")
    assert len(out) == 2 and not isinstance(out[1], Exception)
    assert out[1].echo.raw == next_echo and out[1].echo.string == ""
    if next_echo.startswith(b"MS"):
        assert isinstance(out[1], ScanReply) and out[1].timestamp_ms == 1234 and out[1].distances.tolist() == [100]


def test_echo_with_an_ordinary_string_keeps_it():
    out = ScipParser().feed(encode_reply(b"MS0540054001000;scan-7", "00"))
    assert out[0].echo.string == "scan-7"


def _scan_frames_bytewise(buf, verify, line_payload):
    """drivers.hokuyo.scip_jit.scan_frames as it was before it copied each data line as a slice (the data
    characters one at a time), run as plain Python: the reference."""
    lf = np.flatnonzero(buf == 0x0A)
    frames = np.empty((lf.size // 4, 4), np.int64)
    data = np.empty(buf.size, np.uint8)
    offsets = np.zeros(lf.size // 4 + 1, np.int64)
    m = done = li = 0
    for bi in range(lf.size - 1):
        if lf[bi + 1] - lf[bi] != 1:
            continue
        if bi + 1 - li < 4 or lf[li] <= done:
            break
        i2 = lf[li + 1]
        ok = True
        start = i2 + 1
        n_out = offsets[m]
        for k in range(li + 2, bi + 1):
            end = lf[k]
            n = end - start
            first, last = k == li + 2, k == bi
            if (n != 5) if first else ((n < 2) if last else (n != line_payload + 1)):
                ok = False
                break
            if verify and (int(buf[start:end - 1].astype(np.int64).sum()) & 0x3F) + 0x30 != buf[end - 1]:
                ok = False
                break
            if not first:
                for j in range(start, end - 1):
                    data[n_out] = buf[j]
                    n_out += 1
            start = end + 1
        if not ok:
            break
        frames[m] = done, lf[li], i2, lf[bi + 1]
        m += 1
        offsets[m] = n_out
        done = lf[bi + 1] + 1
        li = bi + 2
    return frames[:m], data[:offsets[m]], offsets[:m + 1]


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(scan_messages(), min_size=1, max_size=3), st.data(), st.booleans())
def test_scan_frames_equals_the_bytewise_copy(cases, data, verify):
    """Whole messages, then a flipped, inserted or deleted byte or a cut anywhere (short lines, bad
    checksums, lost line ends), with and without checksum verification."""
    from drivers.hokuyo.scip_jit import scan_frames

    buf = bytearray(b"".join(c[0] for c in cases))
    kind = data.draw(st.sampled_from(["none", "flip", "insert", "delete", "cut"]))
    at = data.draw(st.integers(0, len(buf) - 1))
    if kind == "flip":
        buf[at] ^= 1 << data.draw(st.integers(0, 7))
    elif kind == "insert":
        buf[at:at] = bytes([data.draw(st.sampled_from([0x0A, 0x26, 0x30, 0x7F]))])
    elif kind == "delete":
        del buf[at]
    elif kind == "cut":
        del buf[at:]
    a = np.frombuffer(bytes(buf), np.uint8)
    got, want = scan_frames(a, verify, LINE_PAYLOAD), _scan_frames_bytewise(a, verify, LINE_PAYLOAD)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and np.array_equal(g, w)
