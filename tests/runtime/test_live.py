"""Live view (--live): the recording's topics over the Foxglove WebSocket protocol, checked with Foxglove's
own client (@foxglove/ws-protocol) and ROS 2 CDR decoder (@foxglove/rosmsg2-serialization) under Node.

The Node test tool lives in tests/runtime/live_client (scripts/dev.sh installs it with npm); the tests
that need it skip with the reason when node or the tool is missing.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from runtime import messages as M
from runtime.live import LIVE_TOPICS, Fanout, LiveView
from runtime.output_args import LiveViewError, parse_address
from runtime.pipeline import ScanResult
from runtime.sink import RecordingSink
from tests.runtime.factories import make_odom, make_scan

CLIENT = Path(__file__).resolve().parent / "live_client"
pytestmark = pytest.mark.timeout(120)


def _need_client() -> None:
    if shutil.which("node") is None:
        pytest.skip(reason="node is not installed (the live view is checked with Foxglove's Node client)")
    if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.skip(reason="the Node test client is not installed: scripts/dev.sh setup (npm ci in tests/runtime/live_client)")


def _client(url: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen(["node", str(CLIENT / "client.js"), url, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _report(proc: subprocess.Popen, timeout: float = 60.0) -> dict:
    out, err = proc.communicate(timeout=timeout)
    assert out.strip(), f"no report from the client: {err}"
    return json.loads(out.strip().splitlines()[-1])


def _wait_stuck(proc: subprocess.Popen) -> None:
    line = proc.stdout.readline()
    assert line.strip() == "stuck", proc.stderr.read() if proc.poll() is not None else line


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_address_port_alone_is_loopback():
    assert parse_address("8765") == ("127.0.0.1", 8765)
    assert parse_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_address("[::1]:9000") == ("::1", 9000)
    for bad in ("abc", "host:", "70000", "host:port"):
        with pytest.raises(LiveViewError):
            parse_address(bad)


def test_port_in_use_is_one_clear_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(LiveViewError, match="cannot serve the live view on 127.0.0.1"):
            LiveView("127.0.0.1", s.getsockname()[1])


def test_maps_are_throttled_and_raw_bytes_not_served():
    with LiveView("127.0.0.1", 0, map_period=60.0) as lv:
        assert lv.write("/map", b"\x00\x01\x00\x00", 1)
        assert not lv.write("/map", b"\x00\x01\x00\x00", 2)
        assert lv.write("/glass/map", b"\x00\x01\x00\x00", 2)  # each map topic on its own clock
        assert not lv.write("/raw/laser", b"", 3)
        assert lv.stats.throttled == 1
    assert "/raw/laser" not in LIVE_TOPICS and set(LIVE_TOPICS) >= {
        "/scan", "/odom", "/tf", "/tf_static", "/pose", "/glass/beams", "/map", "/glass/map"}


def _feed(sink: RecordingSink, k: int) -> None:
    """One round of every topic through the recording sink (the runtime's path)."""
    from glassmap.types import PoseEstimate

    scan = make_scan(10.0 + 0.025 * k, seq=k)
    odom = make_odom(10.0 + 0.025 * k, x=0.01 * k)
    sink.odometry(odom)
    sink.scan(scan)
    est = PoseEstimate(stamp=scan.stamp, x=1.0 + 0.01 * k, y=2.0, yaw=0.3,
                       covariance=np.diag([1e-4, 2e-4, 3e-5]))
    p = np.full(scan.ranges.shape, 0.25)
    sink.result(ScanResult(scan=scan, estimate=est, laser_pose=np.array([1.1 + 0.01 * k, 2.0, 0.3]),
                           p_glass=p, odom=odom))
    sink.cmd_vel(scan.stamp, 0.2, 0.1)
    ts = M.typestore()
    ns = sink.tb.ns(scan.stamp)
    occ = M.occupancy_grid_msg(np.full((3, 4), 0.9), (-1.0, -2.0), 0.05, ns)
    glass = M.glass_grid_msg(np.full((3, 4), 0.75, np.float32), (-1.0, -2.0), 0.05, ns)
    sink.maps(ns, bytes(ts.serialize_cdr(occ, "nav_msgs/msg/OccupancyGrid")),
              bytes(ts.serialize_cdr(glass, "foxglove_msgs/msg/Grid")))


def test_foxglove_client_decodes_every_topic_as_recorded(tmp_path):
    _need_client()
    from runtime.recorder import McapRecorder, read_mcap

    wanted = ["/scan", "/odom", "/tf", "/tf_static", "/pose", "/glass/beams", "/map", "/glass/map", "/cmd_vel"]
    tb = M.TimeBase(1_700_000_000_000_000_000)
    with LiveView("127.0.0.1", 0, map_period=0.0) as lv:
        rec = McapRecorder(tmp_path / "r.mcap")
        client = _client(lv.url, "--seconds", "30", "--until", ",".join(wanted))
        sink = RecordingSink(Fanout(rec, lv), tb, record_raw=False)
        k = 0
        while client.poll() is None and k < 1000:  # until the client has one message of each topic
            sink._static_sent = False  # /tf_static again for a late subscriber
            _feed(sink, k)
            k += 1
            time.sleep(0.02)
        report = _report(client)
        rec.close()
    assert client.returncode == 0, report
    ch = report["channels"]
    for t in wanted:  # the recording's schema names and encodings
        assert ch[t] == {"schemaName": LIVE_TOPICS[t], "encoding": "cdr", "schemaEncoding": "ros2msg"}
    got = report["topics"]
    recorded = {}
    for topic, _, _, msg in read_mcap(tmp_path / "r.mcap"):
        recorded.setdefault(topic, msg)
    assert set(wanted) <= set(recorded)
    scan = got["/scan"]["last"]
    assert scan["ranges"]["len"] == 1081 and scan["header"]["frame_id"] == "laser"
    assert scan["angle_increment"] == pytest.approx(recorded["/scan"].angle_increment)
    beams = got["/glass/beams"]["last"]
    assert beams["intensities"]["head"][0] == pytest.approx(0.25)
    odom = got["/odom"]["last"]
    assert odom["child_frame_id"] == "base_link" and odom["pose"]["covariance"]["len"] == 36
    pose = got["/pose"]["last"]
    assert pose["header"]["frame_id"] == "map" and pose["pose"]["pose"]["position"]["y"] == pytest.approx(2.0)
    assert pose["pose"]["covariance"]["head"][0] == pytest.approx(1e-4)
    frames = {(t["header"]["frame_id"]) for t in [got["/tf"]["last"]["transforms"]["head"][0],
                                                  got["/tf_static"]["last"]["transforms"]["head"][0]]}
    assert frames <= {"map", "odom", "base_link"}
    occ = got["/map"]["last"]
    assert (occ["info"]["width"], occ["info"]["height"]) == (4, 3) and occ["data"]["head"][0] == 90
    grid = got["/glass/map"]["last"]
    assert grid["column_count"] == 4 and grid["cell_stride"] == 8 and grid["data"]["len"] == 3 * 4 * 8
    assert [f["name"] for f in [grid["fields"]["head"][0]]] == ["p_glass"]
    assert got["/cmd_vel"]["last"]["linear"]["x"] == pytest.approx(0.2)
    # log times are the messages' stamps (wall clock through the time base)
    assert int(got["/odom"]["log_time"]) > tb.offset_ns


def test_stuck_viewer_never_blocks_the_producer_and_others_still_get_data():
    _need_client()
    n = 300
    big = bytes(256 * 1024)  # a 256 kB map message: the stuck client's TCP window fills quickly
    with LiveView("127.0.0.1", 0, map_period=0.0, queue_size=32, backlog=8) as lv:
        stuck = _client(lv.url, "--stuck")
        try:
            _wait_stuck(stuck)
            queued = 0
            for k in range(n):
                # write() never waits: a full queue drops (and counts) instead
                queued += lv.write("/glass/map", big, k + 1)
                time.sleep(0.002)
            deadline = time.monotonic() + 60
            while lv.stats.total_sent < queued and time.monotonic() < deadline:
                time.sleep(0.05)
            # the sending thread was never held up by the client that does not read
            assert lv.stats.total_sent == queued
            assert queued + lv.stats.total_dropped == n
            assert stuck.poll() is None  # still connected, still not reading
            # a second viewer still gets fresh data
            reader = _client(lv.url, "--seconds", "20", "--until", "/odom")
            while reader.poll() is None:
                lv.write("/odom", M.odometry_msg(make_odom(1.0), 10**9), 10**9)
                time.sleep(0.02)
            assert reader.returncode == 0
            assert _report(reader)["topics"]["/odom"]["count"] >= 1
            lv.close()  # returns although a viewer still does not read
        finally:
            stuck.kill()
            stuck.wait()


def test_replay_publishes_as_the_live_run(tmp_path):
    _need_client()
    from runtime.recorder import McapRecorder
    from runtime.replay import replay_file

    path = tmp_path / "small.mcap"
    with McapRecorder(path) as rec:
        sink = RecordingSink(rec, M.TimeBase(1_700_000_000_000_000_000))
        for k in range(30):
            sink.odometry(make_odom(10.0 + 0.025 * k, x=0.002 * k))
            sink.scan(make_scan(10.0 + 0.025 * k + 0.001, seq=k))
    wanted = ["/scan", "/odom", "/tf", "/pose", "/glass/beams", "/map", "/glass/map"]
    with LiveView("127.0.0.1", 0, map_period=0.0) as lv:
        client = _client(lv.url, "--seconds", "30", "--until", ",".join(wanted))
        assert client.stderr.readline().strip() == "subscribed"
        res = replay_file(path, progress=False, live=lv)
        report = _report(client)
    assert res.scans == 30
    assert client.returncode == 0, report
    assert report["topics"]["/scan"]["count"] >= 1 and report["topics"]["/map"]["count"] >= 1


@pytest.mark.slow
def test_demo_serves_live_view_with_a_stuck_and_a_reading_viewer(tmp_path):
    """The full runtime with --live: a viewer that never reads does not stop the 40 Hz loop, and a normal
    viewer decodes every mapping topic while the robot drives."""
    _need_client()
    from runtime.config import RuntimeConfig
    from runtime.demo import DemoOptions, run_demo

    port = _free_port()
    cfg = RuntimeConfig()
    cfg.output.live = str(port)
    cfg.output.map_publish_period = 0.5
    cfg.output.live_map_period = 0.5
    wanted = ["/scan", "/odom", "/tf", "/tf_static", "/pose", "/glass/beams", "/map", "/glass/map"]
    clients: list[subprocess.Popen] = []

    async def viewers() -> None:
        while True:  # the server is up once the runtime has started
            try:
                _, w = await asyncio.open_connection("127.0.0.1", port)
                w.close()
                break
            except OSError:
                await asyncio.sleep(0.1)
        clients.append(_client(f"ws://127.0.0.1:{port}", "--stuck"))
        clients.append(_client(f"ws://127.0.0.1:{port}", "--seconds", "60", "--until", ",".join(wanted)))

    async def main():
        v = asyncio.create_task(viewers())
        res = await run_demo(DemoOptions(speed=2.0, duration=10.0, out_dir=str(tmp_path), progress=False,
                                         record=False, config=cfg))
        await v
        return res

    try:
        res = asyncio.run(main())
        stuck, reader = clients
        report = _report(reader)
    finally:
        for c in clients:
            c.kill()
            c.wait()
    s = res.summary
    assert s.live == f"ws://127.0.0.1:{port}"
    assert s.live_sent > 0
    assert s.stop_reason == "duration 10 s (emulated) reached"
    assert s.stages.scans_processed > 5 and s.stages.scans_received > 150
    assert reader.returncode == 0, report
    for t in wanted:
        assert report["topics"][t]["count"] >= 1, t
    assert report["topics"]["/scan"]["last"]["ranges"]["len"] == 1081
