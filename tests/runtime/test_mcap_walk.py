"""The record walker gives the raw replay the same messages as the mcap library, on whole, cut or damaged files."""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from drivers.capture import Capture
from runtime import messages as M
from runtime.mcap_walk import iter_channel_messages
from runtime.readers import RawChunk, iter_raw_chunks
from runtime.recorder import McapRecorder, iter_mcap_raw
from tests.runtime.factories import make_odom, make_scan

CAPTURES = Path(__file__).resolve().parents[1] / "fakes" / "captures"


def _is_raw(topic: str, msgtype: str) -> bool:
    return msgtype == M.RAW_BYTES_TYPE


def _library(path, wanted=_is_raw):
    return [r for r in iter_mcap_raw(path) if wanted(r.topic, r.msgtype)]


def _rosbags_chunks(path) -> list[RawChunk]:
    """iter_raw_chunks as it was: the library's records, decoded by rosbags."""
    ts = M.typestore()
    out = []
    for r in _library(path):
        msg = ts.deserialize_cdr(r.data, r.msgtype)
        out.append(RawChunk(msg.header.frame_id, msg.host_time, msg.direction, msg.url, bytes(msg.data)))
    return out


def _record(path: Path, compression: str = "zstd", maps: bool = False) -> Path:
    """A recording as the runtime writes it: a laser and a base capture's bytes between scans, odometry and
    /tf, in several chunks; with ``maps``, a glass map (larger than a chunk) every 20 events."""
    laser = Capture.load(CAPTURES / "hokuyo-me-stream.jsonl")
    base = Capture.load(CAPTURES / "pioneer-p3dx-drive.jsonl")
    tb = M.TimeBase(offset_ns=1_700_000_000_000_000_000)
    events = sorted([(c.t, "laser", c) for c in laser.chunks] + [(c.t + 0.001, "base", c) for c in base.chunks],
                    key=lambda e: e[0])
    urls = {"laser": "tcp://10.0.0.2:10940", "base": "serial:///dev/ttyS0"}
    with McapRecorder(path, chunk_size=20_000, compression=compression) as rec:
        for i, (t, dev, c) in enumerate(events):
            ns = tb.ns(100.0 + t)
            rec.write(f"/raw/{dev}", M.raw_bytes_msg(ns, dev, c.direction, 100.0 + t, c.data, url=urls[dev]), ns)
            if i % 5 == 0:
                rec.write("/scan", M.laser_scan_msg(make_scan(100.0 + t, i, n=200), ns), ns)
                rec.write("/odom", M.odometry_msg(make_odom(100.0 + t, float(i)), ns), ns)
                rec.write("/tf", M.tf_msg([M.transform_stamped(ns, "odom", "base_link", 0.1 * i, 0.0, 0.0)]), ns)
            if maps and i % 20 == 10:
                conf = np.full((60, 60), np.nan, dtype=np.float32)
                conf[10:50, 30] = 0.01 * i
                rec.write("/glass/map", M.glass_grid_msg(conf, (0.0, 0.0), 0.05, ns), ns)
    return path


def _top_level(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, content length) of the top-level records of a complete MCAP file."""
    out, pos = [], 8
    while pos + 9 <= len(data) - 8:
        op, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, length))
        pos += 9 + length
    return out


def _damage_chunk(data: bytearray, off: int) -> None:
    """Overwrite the start of the compressed records of the Chunk record at ``off``: not a zstd frame any more."""
    # the compressed records start after the chunk's fixed fields, its compression name and records length
    name_len = struct.unpack_from("<I", data, off + 9 + 28)[0]
    records = off + 9 + 32 + name_len + 8
    data[records:records + 4] = b"\xde\xad\xbe\xef"


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return _record(tmp_path_factory.mktemp("walk") / "r.mcap")


def test_same_raw_chunks_as_the_library_path(recording):
    chunks = list(iter_raw_chunks(recording))
    assert len(chunks) > 90 and {c.device for c in chunks} == {"laser", "base"}
    assert sum(op == 0x06 for _, op, _ in _top_level(recording.read_bytes())) > 3  # several chunks
    assert chunks == _rosbags_chunks(recording)
    assert list(iter_channel_messages(recording, _is_raw)) == _library(recording)


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_other_chunk_compressions(tmp_path, compression):
    path = _record(tmp_path / "r.mcap", compression)
    assert list(iter_raw_chunks(path)) == _rosbags_chunks(path)


def test_any_choice_of_channels_as_the_library(recording):
    for wanted in (lambda t, m: True, lambda t, m: t == "/odom", lambda t, m: False,
                   lambda t, m: m.endswith("LaserScan") or t == "/raw/base"):
        assert list(iter_channel_messages(recording, wanted)) == _library(recording, wanted)


def test_foreign_channels_are_skipped(tmp_path):
    path = tmp_path / "foreign.mcap"
    ts = M.typestore()
    raw = bytes(ts.serialize_cdr(M.raw_bytes_msg(5, "laser", "rx", 1.5, b"VV\n00P\n\n", "tcp://x"), M.RAW_BYTES_TYPE))
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="test")
        other = w.register_schema("other_msgs/msg/Blob", "ros2msg", b"uint8[] data\n")
        mine = w.register_schema(M.RAW_BYTES_TYPE, "ros2msg", M.msgdef(M.RAW_BYTES_TYPE).encode())
        c_other = w.register_channel("/raw/other", "cdr", other)  # a /raw/ topic, not the RawBytes type
        c_none = w.register_channel("/raw/none", "cdr", 0)  # no schema at all
        c_mine = w.register_channel("/raw/laser", "cdr", mine)
        for i in range(6):
            w.add_message(c_other, i, b"\x00\x01\x00\x00garbage", i)
            w.add_message(c_none, i, b"junk", i)
            w.add_message(c_mine, i, raw, i)
        w.finish()
    seen = []

    def wanted(topic: str, msgtype: str) -> bool:
        seen.append(topic)
        return _is_raw(topic, msgtype)

    got = list(iter_channel_messages(path, wanted))
    assert [r.topic for r in got] == ["/raw/laser"] * 6 and {r.data for r in got} == {raw}
    assert sorted(seen) == ["/raw/laser", "/raw/none", "/raw/other"]  # decided once per channel
    assert list(iter_raw_chunks(path)) == [RawChunk("laser", 1.5, "rx", "tcp://x", b"VV\n00P\n\n")] * 6


def test_a_file_cut_anywhere_gives_what_the_library_gives(recording, tmp_path, caplog):
    data = recording.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    counts = []
    for cut in list(range(0, len(data), max(1, len(data) // 60))) + [len(data) - 1]:
        cut_path.write_bytes(data[:cut])
        with caplog.at_level(logging.INFO, logger="runtime.mcap_walk"):
            caplog.clear()
            got = list(iter_channel_messages(cut_path, _is_raw))
        assert got == _library(cut_path), cut
        assert all(r.levelno == logging.INFO for r in caplog.records)  # said quietly
        if cut < len(data) - 37:  # before the footer (29 bytes) and the closing magic (8)
            assert caplog.records
        counts.append(len(got))
    assert counts[0] == 0 and counts == sorted(counts) and 0 < counts[-1] < len(_library(recording)) + 1


def test_a_file_without_summary_reads_whole(recording, tmp_path):
    data = recording.read_bytes()
    data_end = next(off for off, op, _ in _top_level(data) if op == 0x0F)
    path = tmp_path / "nosummary.mcap"
    path.write_bytes(data[:data_end])
    assert list(iter_raw_chunks(path)) == list(iter_raw_chunks(recording))


def test_a_damaged_chunk_stops_the_reading_before_it(recording, tmp_path, caplog):
    data = bytearray(recording.read_bytes())
    chunks = [(off, length) for off, op, length in _top_level(bytes(data)) if op == 0x06]
    off, length = chunks[2]
    _damage_chunk(data, off)
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    before = tmp_path / "before.mcap"
    before.write_bytes(bytes(data[:off]))  # the file up to the damaged chunk
    with caplog.at_level(logging.INFO, logger="runtime.mcap_walk"):
        got = list(iter_channel_messages(path, _is_raw))
    assert got == _library(before) == _library(path) and len(got) > 0
    assert any("damaged" in r.getMessage() for r in caplog.records)


def test_records_running_past_their_chunk_stop_the_reading(tmp_path, caplog):
    path = _record(tmp_path / "plain.mcap", "none")
    data = bytearray(path.read_bytes())
    off, length = [(o, n) for o, op, n in _top_level(bytes(data)) if op == 0x06][1]
    first_inner = off + 9 + 32 + 0 + 8  # compression "" has no name bytes
    assert data[first_inner] in (0x03, 0x04, 0x05)
    struct.pack_into("<Q", data, first_inner + 1, length * 2)  # the chunk's first record overruns it
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    before = tmp_path / "before.mcap"
    before.write_bytes(bytes(data[:off]))
    with caplog.at_level(logging.INFO, logger="runtime.mcap_walk"):
        got = list(iter_channel_messages(bad, _is_raw))
    assert got == _library(before) and len(got) > 0
    assert any("damaged" in r.getMessage() for r in caplog.records)


def test_not_mcap_gives_nothing(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"PK\x03\x04 not an mcap file at all")
    assert list(iter_channel_messages(path, _is_raw)) == []
    path.write_bytes(b"")
    assert list(iter_channel_messages(path, _is_raw)) == []


def _chunk_topics(path: Path) -> list[set[str]]:
    """The topics of the messages in each chunk, in file order (the summary's Chunk Index records)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return [{summary.channels[c].topic for c in ci.message_index_offsets}
            for ci in sorted(summary.chunk_indexes, key=lambda ci: ci.chunk_start_offset)]


def test_a_map_gets_a_chunk_of_its_own_that_a_raw_reading_skips(tmp_path):
    path = _record(tmp_path / "maps.mcap", maps=True)
    topics = _chunk_topics(path)
    assert topics.count({"/glass/map"}) >= 3 and not any("/glass/map" in t and len(t) > 1 for t in topics)
    for wanted in (_is_raw, lambda t, m: True, lambda t, m: t == "/glass/map"):
        assert list(iter_channel_messages(path, wanted)) == _library(path, wanted)
    # a damaged map chunk: the raw reading never decompresses it, the library stops there
    data = bytearray(path.read_bytes())
    chunks = [off for off, op, _ in _top_level(bytes(data)) if op == 0x06]
    _damage_chunk(data, chunks[[i for i, t in enumerate(topics) if t == {"/glass/map"}][1]])
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    assert list(iter_channel_messages(damaged, _is_raw)) == _library(path)
    assert len(_library(damaged)) < len(_library(path))
    # without the summary nothing says what a chunk holds: every chunk is decompressed, and the reading stops
    # at the damaged one as the library's does
    cut = tmp_path / "nosummary.mcap"
    cut.write_bytes(bytes(data[:next(off for off, op, _ in _top_level(bytes(data)) if op == 0x0F)]))
    got = list(iter_channel_messages(cut, _is_raw))
    assert got == _library(cut) and len(got) < len(_library(path))


def test_a_channel_defined_in_a_chunk_without_its_messages_is_still_read(tmp_path):
    """A chunk can close between a channel's definition and its first message (the recorder cuts chunks by
    time): the chunk that defines the channel then holds no message of it and is skipped, and the channel's
    messages in later chunks must still come out (the summary defines every channel)."""
    path = tmp_path / "late.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD, chunk_size=1)  # a chunk closes after each message
        w.start(profile="ros2", library="test")
        sid = w.register_schema("test_msgs/msg/Blob", "ros2msg", b"uint8[] data\n")
        busy = w.register_channel("/busy", "cdr", sid)
        late = w.register_channel("/late", "cdr", sid)  # defined in the first chunk, which holds only /busy
        w.add_message(busy, 1, b"b1", 1)
        for i in range(3):
            w.add_message(late, 10 + i, b"l%d" % i, 10 + i)
        w.finish()
    chunks = _chunk_topics(path)
    assert chunks == [{"/busy"}, {"/late"}, {"/late"}, {"/late"}]
    want = lambda t, m: t == "/late"  # noqa: E731
    got = list(iter_channel_messages(path, want))
    assert [r.data for r in got] == [b"l0", b"l1", b"l2"] and got == _library(path, want)
