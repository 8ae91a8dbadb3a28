"""Replay readers: glassmap MCAP, ROS 2 bags and ROS 1 bags give the same Scans and Odometry."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from drivers.capture import Capture
from glassmap.types import Scan
from runtime import messages as M
from runtime.readers import ReplayInputError, iter_messages, read_captures, read_metadata
from runtime.recorder import McapRecorder
from runtime.sink import RecordingSink, recording_metadata
from tests.runtime.factories import make_odom, make_scan

STAMPS = [(0.00, "odom"), (0.01, "scan"), (0.05, "scan"), (0.10, "odom"), (0.11, "scan")]


def items():
    out = []
    for i, (t, kind) in enumerate(STAMPS):
        out.append(make_odom(100.0 + t, x=float(i)) if kind == "odom" else make_scan(100.0 + t, seq=i))
    return out


def check_items(got, tolerance_stamp=1e-6, odom_cov=True):
    want = items()
    assert [type(g) for g in got] == [type(w) for w in want]
    for g, w in zip(got, want):
        if isinstance(w, Scan):
            np.testing.assert_allclose(g.ranges, w.ranges.astype(np.float32), rtol=0)
            np.testing.assert_allclose(g.intensities, w.intensities)
            assert g.geometry.angle_min == pytest.approx(w.geometry.angle_min)
            assert g.geometry.angle_increment == pytest.approx(w.geometry.angle_increment)
            assert g.stamp == pytest.approx(w.stamp, abs=tolerance_stamp)
        else:
            assert (g.x, g.y, g.yaw) == pytest.approx((w.x, w.y, w.yaw))
            assert g.stamp == pytest.approx(w.stamp, abs=tolerance_stamp)
            if odom_cov:
                np.testing.assert_allclose(g.covariance, w.covariance)


def test_glassmap_recording_gives_back_the_live_stamps(tmp_path):
    path = tmp_path / "rec.mcap"
    tb = M.TimeBase(offset_ns=1_763_000_000_123_456_789)
    rec = McapRecorder(path, metadata=recording_metadata(tb, note="test"))
    sink = RecordingSink(rec, tb)
    raw = sink.tap("laser", "tcp://127.0.0.1:10940")
    raw("tx", 99.0, b"MD0000108000001\n")
    raw("rx", 99.5, b"MD0000108000001\n00P\n\n")
    for it in items():
        sink.scan(it) if isinstance(it, Scan) else sink.odometry(it)
    rec.close()
    assert read_metadata(path)["note"] == "test"
    got = list(iter_messages(path))
    check_items(got)
    assert [g.seq for g in got if isinstance(g, Scan)] == [1, 2, 3]  # numbered in recording order (for the log)
    caps = read_captures(path)
    assert isinstance(caps["laser"], Capture)
    assert [(c.t, c.direction) for c in caps["laser"].chunks] == [(0.0, "tx"), (0.5, "rx")]
    assert caps["laser"].tx_bytes() == b"MD0000108000001\n"


def _scan_msg(ts, s: Scan):
    return M.laser_scan_msg(s, round(s.stamp * 1e9))


def test_ros2_bag_with_odometry(tmp_path):
    path = tmp_path / "bag2"
    ts = M.typestore()
    with Writer2(path, version=9) as w:
        cs = w.add_connection("/base_scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        co = w.add_connection("/wheel_odom", "nav_msgs/msg/Odometry", typestore=ts)
        for it in items():
            ns = round(it.stamp * 1e9)
            if isinstance(it, Scan):
                w.write(cs, ns, ts.serialize_cdr(M.laser_scan_msg(it, ns), "sensor_msgs/msg/LaserScan"))
            else:
                w.write(co, ns, ts.serialize_cdr(M.odometry_msg(it, ns), "nav_msgs/msg/Odometry"))
    check_items(list(iter_messages(path)))


def test_ros1_bag_with_tf_only(tmp_path):
    path = tmp_path / "old.bag"
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    ts1.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    T = ts1.types
    with Writer1(path) as w:
        cs = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts1)
        ctf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts1)
        for i, it in enumerate(items()):
            ns = round(it.stamp * 1e9)
            stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
            hdr = T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="laser")
            if isinstance(it, Scan):
                m2 = M.laser_scan_msg(it, ns)
                msg = T["sensor_msgs/msg/LaserScan"](
                    header=hdr, angle_min=m2.angle_min, angle_max=m2.angle_max, angle_increment=m2.angle_increment,
                    time_increment=m2.time_increment, scan_time=m2.scan_time, range_min=m2.range_min,
                    range_max=m2.range_max, ranges=m2.ranges, intensities=m2.intensities)
                w.write(cs, ns, ts1.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))
            else:
                tr = T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=it.x, y=it.y, z=0.0),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(it.yaw / 2), w=np.cos(it.yaw / 2)))
                tfs = T["geometry_msgs/msg/TransformStamped"](
                    header=T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="odom"),
                    child_frame_id="base_link", transform=tr)
                w.write(ctf, ns, ts1.serialize_ros1(T["tf2_msgs/msg/TFMessage"](transforms=[tfs]),
                                                   "tf2_msgs/msg/TFMessage"))
    check_items(list(iter_messages(path)), odom_cov=False)


def test_bad_inputs_give_clear_errors(tmp_path):
    with pytest.raises(ReplayInputError, match="no such file"):
        list(iter_messages(tmp_path / "missing.mcap"))
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(ReplayInputError, match="unknown file kind"):
        list(iter_messages(tmp_path / "x.txt"))
    empty = tmp_path / "noscan.mcap"
    with McapRecorder(empty) as rec:
        rec.write("/odom", M.odometry_msg(make_odom(1.0), 1), 1)
    with pytest.raises(ReplayInputError, match="no sensor_msgs/LaserScan"):
        list(iter_messages(empty))


def test_a_bag_does_not_say_where_the_robot_started_and_the_replay_says_so(tmp_path):
    import dataclasses
    import json

    from runtime.config import RuntimeConfig
    from runtime.replay import recorded_config, start_pose_note

    bag = tmp_path / "bag2"
    ts = M.typestore()
    with Writer2(bag, version=9) as w:
        cs = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        s = make_scan(1.0)
        w.write(cs, 10**9, ts.serialize_cdr(M.laser_scan_msg(s, 10**9), "sensor_msgs/msg/LaserScan"))
    cfg = recorded_config(bag)
    assert "--mapping.initial_x" in start_pose_note(bag, cfg)
    moved = dataclasses.replace(cfg, mapping=dataclasses.replace(cfg.mapping, initial_x=1.5))
    assert start_pose_note(bag, moved) is None  # given by the user
    rec = tmp_path / "rec.mcap"
    mapping = json.dumps(dataclasses.asdict(RuntimeConfig().mapping))
    with McapRecorder(rec, metadata=recording_metadata(M.TimeBase(offset_ns=0), mapping=mapping)) as r:
        r.write("/odom", M.odometry_msg(make_odom(1.0), 1), 1)
    assert start_pose_note(rec, recorded_config(rec)) is None  # a glassmap recording stores its start pose
    assert recorded_config(rec).mapping.registration_sigma == "map" and cfg.mapping.registration_sigma == "map"
    assert recorded_config(rec).mapping.glass_scans == "keys"
    old = tmp_path / "old.mcap"  # made before mapping.registration_sigma and glass_scans: replayed as then
    old_mapping = {k: v for k, v in json.loads(mapping).items() if k not in ("registration_sigma", "glass_scans")}
    with McapRecorder(old, metadata=recording_metadata(M.TimeBase(offset_ns=0), mapping=json.dumps(old_mapping))) as r:
        r.write("/odom", M.odometry_msg(make_odom(1.0), 1), 1)
    assert recorded_config(old).mapping.registration_sigma == "anchor"
    assert recorded_config(old).mapping.glass_scans == "all"  # every scan was registered then
