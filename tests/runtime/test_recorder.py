"""The MCAP recorder: ROS 2 profile, readable by rosbags' AnyReader, crash safety, no silent drops."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.highlevel import AnyReader

from glassmap.types import PoseEstimate
from runtime import messages as M
from runtime.recorder import McapRecorder, iter_mcap_raw, read_mcap, recover_mcap
from tests.runtime.factories import make_odom, make_scan
from tests.helpers import wait_until

ROOT = Path(__file__).resolve().parents[2]


def test_round_trip_through_anyreader(tmp_path):
    path = tmp_path / "r.mcap"
    tb = M.TimeBase(offset_ns=1_700_000_000_000_000_000)
    scan = make_scan(12.5, seq=3)
    with McapRecorder(path) as rec:
        ns = tb.ns(scan.stamp)
        rec.write("/scan", M.laser_scan_msg(scan, ns), ns)
        rec.write("/odom", M.odometry_msg(make_odom(12.4, 2.0), ns), ns)
        rec.write("/pose", M.pose_with_covariance_msg(PoseEstimate(12.5, 1.0, 2.0, 0.5, np.diag([1e-3, 2e-3, 1e-4])),
                                                      ns), ns)
        rec.write("/raw/laser", M.raw_bytes_msg(ns, "laser", "rx", 12.5, b"ME0000108000001\n"), ns)
    assert rec.stats.total_written == 4 and rec.stats.total_dropped == 0
    with AnyReader([path]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics["/scan"] == "sensor_msgs/msg/LaserScan"
        assert topics["/raw/laser"] == "glassmap_msgs/msg/RawBytes"
        got = {c.topic: (t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()}
    t, msg = got["/scan"]
    assert t == 1_700_000_000_000_000_000 + 12_500_000_000
    assert M.stamp_to_ns(msg.header.stamp) == t  # stamped with the scan's acquisition time
    assert msg.header.frame_id == "laser"
    assert len(msg.ranges) == 1081 and msg.angle_min == pytest.approx(-3 * np.pi / 4)
    assert msg.angle_max == pytest.approx(3 * np.pi / 4)
    np.testing.assert_allclose(msg.ranges, scan.ranges.astype(np.float32))  # NaN and inf kept
    np.testing.assert_allclose(msg.intensities, 103.0)
    pose = got["/pose"][1].pose
    assert M.yaw_of(pose.pose.orientation) == pytest.approx(0.5)
    assert M.cov3(pose.covariance) == pytest.approx(np.diag([1e-3, 2e-3, 1e-4]))
    odom = M.odometry_from_msg(got["/odom"][1], 0.0)
    assert (odom.x, odom.y, odom.yaw) == pytest.approx((2.0, 1.0, 0.2))
    assert bytes(got["/raw/laser"][1].data) == b"ME0000108000001\n"


def test_glass_grid_colours_and_values():
    conf = np.full((4, 5), np.nan, np.float32)
    conf[1, 2], conf[2, 3], conf[3, 0] = 1.0, 0.0, 0.5
    msg = M.glass_grid_msg(conf, (-1.0, 2.0), 0.05, 0)
    assert msg.column_count == 5 and msg.cell_stride == 8 and msg.row_stride == 40
    assert msg.cell_size.x == 0.05 and msg.pose.position.x == -1.0
    v = M.grid_values(msg)
    assert v[1, 2] == 1.0 and v[2, 3] == 0.0 and np.isnan(v[0, 0])
    rgba = np.asarray(msg.data).reshape(4, 5, 8)[:, :, 4:]
    assert tuple(rgba[1, 2]) == (255, 0, 0, 255)  # glass: red
    assert tuple(rgba[2, 3]) == (0, 0, 255, 255)  # not glass: blue
    assert tuple(rgba[3, 0]) == (128, 128, 128, 255)  # uncertain: gray
    assert rgba[0, 0, 3] == 0  # not a wall: transparent


def test_occupancy_grid_values():
    p = np.array([[0.5, 0.9], [0.1, np.nan]])
    msg = M.occupancy_grid_msg(p, (0.0, 0.0), 0.05, 0)
    assert list(msg.data) == [-1, 90, 10, -1]
    assert (msg.info.width, msg.info.height) == (2, 1 * 2)


def _reference_occupancy_data(p: np.ndarray) -> np.ndarray:
    """/map cells by the rule, over the whole map in float64: 0..100, -1 unknown (NaN or within 1e-3 of 0.5)."""
    p = np.asarray(p, dtype=np.float64)
    data = np.full(p.shape, -1, dtype=np.int8)
    known = np.isfinite(p) & (np.abs(p - 0.5) > 1e-3)
    data[known] = np.clip(np.round(p[known] * 100), 0, 100).astype(np.int8)
    return data.reshape(-1)


def _reference_glass_cells(c: np.ndarray) -> np.ndarray:
    """/glass/map cells by the rule, over the whole map: p_glass, then blue -> gray -> red, alpha 0 off walls."""
    c = np.asarray(c, dtype=np.float32)
    known = np.isfinite(c)
    pk = np.clip(np.where(known, c, 0.5), 0.0, 1.0)
    lo = pk < 0.5
    t = np.where(lo, pk / 0.5, (pk - 0.5) / 0.5)
    rgba = np.stack([np.where(lo, 128 * t, 128 + 127 * t), np.where(lo, 128 * t, 128 * (1 - t)),
                     np.where(lo, 255 - 127 * t, 128 * (1 - t))], axis=-1).astype(np.uint8)
    cells = np.zeros(c.shape + (8,), np.uint8)
    cells[..., :4] = c[..., None].view(np.uint8)
    cells[..., 4:7] = rgba
    cells[..., 7] = np.where(known, 255, 0)
    return cells.reshape(-1)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.integers(0, 2**32 - 1), st.booleans())
def test_map_messages_equal_the_whole_map_rule(h, w, seed, float64):
    """The map messages are built from the known cells only; the bytes are those of the rule applied to
    every cell (unknown, exactly 0.5, just either side of the 1e-3 band, NaN, outside 0..1)."""
    rng = np.random.default_rng(seed)
    p = rng.random((h, w)).astype(np.float32)
    p[rng.random((h, w)) < 0.3] = 0.5
    p[rng.random((h, w)) < 0.1] = np.nan
    near = rng.random((h, w)) < 0.1
    p[near] = (0.5 + rng.choice([-1.0, 1.0], near.sum()) * rng.uniform(0.9e-3, 1.1e-3, near.sum())).astype(np.float32)
    if float64:
        p = p.astype(np.float64)
    assert np.array_equal(np.asarray(M.occupancy_grid_msg(p, (0.0, 0.0), 0.05, 0).data), _reference_occupancy_data(p))
    c = rng.uniform(-0.2, 1.2, (h, w)).astype(np.float32)
    c[rng.random((h, w)) < 0.5] = np.nan
    c[rng.random((h, w)) < 0.05] = 0.5
    assert np.array_equal(np.asarray(M.glass_grid_msg(c, (0.0, 0.0), 0.05, 0).data), _reference_glass_cells(c))


def test_full_queue_drops_are_counted(tmp_path):
    rec = McapRecorder(tmp_path / "q.mcap", queue_size=1)
    release = threading.Event()
    real_channel = rec._channel
    rec._channel = lambda topic: (release.wait(10), real_channel(topic))[1]  # stall the writer thread
    assert rec.write("/rosout", M.log_msg(0, 20, "t", "first"), 0)
    wait_until(lambda: not rec.backlog, what="the writer thread taking the first message", interval=0.001)
    sent = [rec.write("/rosout", M.log_msg(i, 20, "t", "x"), i) for i in range(1, 51)]
    assert sent[0] and sent[1:] == [False] * 49
    assert rec.stats.dropped["/rosout"] == 49
    release.set()
    rec.close()
    assert rec.stats.written["/rosout"] == 2
    assert rec.write("/rosout", M.log_msg(99, 20, "t", "late"), 99) is False  # after close: counted too
    assert rec.stats.dropped["/rosout"] == 50


def test_unknown_topic_is_not_fatal(tmp_path):
    rec = McapRecorder(tmp_path / "u.mcap")
    rec.write("/nope", M.log_msg(0, 20, "t", "x"), 0)
    rec.write("/rosout", M.log_msg(1, 20, "t", "y"), 1)
    rec.close()
    assert rec.stats.errors == 1 and rec.stats.written["/rosout"] == 1


CHILD = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {root!r})
    from runtime import messages as M
    from runtime.recorder import McapRecorder
    from tests.runtime.factories import make_scan
    rec = McapRecorder(sys.argv[1], chunk_interval=0.1, chunk_size=10**9)
    seq = 0
    def burst(n):
        global seq
        for _ in range(n):
            s = make_scan(float(seq), seq)
            rec.write("/scan", M.laser_scan_msg(s, seq), seq)
            seq += 1
    burst(30)
    while rec.backlog or rec.stats.total_written < 30:
        time.sleep(0.01)
    flushed = rec.stats.chunks_flushed
    while rec.stats.chunks_flushed == flushed:
        time.sleep(0.01)
    print("safe", 30, flush=True)
    while True:  # keep writing until killed
        burst(5)
        time.sleep(0.01)
""")


def test_sigkill_mid_recording_keeps_completed_chunks(tmp_path):
    path = tmp_path / "killed.mcap"
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(root=str(ROOT)))
    proc = subprocess.Popen([sys.executable, str(script), str(path)], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.split() == ["safe", "30"]
        time.sleep(0.3)  # a few more chunks and a partial one
    finally:
        proc.kill()
        proc.wait(10)
    seqs = [msg.header.stamp.nanosec for _, _, _, msg in read_mcap(path)]
    assert len(seqs) >= 30
    assert seqs == list(range(len(seqs)))  # in order, nothing missing before the cut
    # The cut-short file has no footer; recover it into a file rosbags reads.
    fixed = tmp_path / "fixed.mcap"
    report = recover_mcap(path, fixed)
    assert report.messages == len(seqs)
    with AnyReader([fixed]) as reader:
        assert sum(c.msgcount for c in reader.connections) == len(seqs)


def test_truncated_anywhere_never_raises(tmp_path):
    path = tmp_path / "t.mcap"
    with McapRecorder(path, chunk_size=2000) as rec:
        for i in range(20):
            s = make_scan(float(i), i, n=100)
            rec.write("/scan", M.laser_scan_msg(s, i), i)
    data = path.read_bytes()
    counts = []
    for cut in range(0, len(data), max(1, len(data) // 40)):
        cut_path = tmp_path / "cut.mcap"
        cut_path.write_bytes(data[:cut])
        counts.append(sum(1 for _ in iter_mcap_raw(cut_path)))
    assert counts == sorted(counts) and counts[-1] <= 20 and counts[0] == 0
