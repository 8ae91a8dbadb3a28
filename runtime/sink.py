"""Turns runtime events into recorded ROS 2 messages (topics in :data:`runtime.messages.TOPICS`).

``/scan`` is stamped with the scan's acquisition time; ``/tf`` carries map -> odom (from each pose estimate
and the odometry at that time) and odom -> base_link (from each odometry message); ``/tf_static`` carries
base_link -> laser. ``/rosout`` gets the program's log through :class:`RosoutHandler`, ``/raw/<device>`` the
bytes of each transport read and write through :meth:`RecordingSink.tap`.
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np

from glassmap.types import Odometry, Scan
from runtime import messages as M
from runtime.pipeline import ScanResult
from runtime.readers import META_NAME
from runtime.recorder import McapRecorder


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) composition a (+) b of (x, y, yaw) poses."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], math.remainder(a[2] + b[2], 2 * math.pi)])


def inverse(a: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2]])


class RecordingSink:
    """Writes what the runtime sees and computes into an :class:`McapRecorder`."""

    def __init__(self, recorder: McapRecorder, time_base: M.TimeBase, *, laser_frame: str = "laser",
                 base_frame: str = "base_link", odom_frame: str = "odom", map_frame: str = "map",
                 record_raw: bool = True) -> None:
        self.rec = recorder
        self.tb = time_base
        self.laser_frame, self.base_frame = laser_frame, base_frame
        self.odom_frame, self.map_frame = odom_frame, map_frame
        self.record_raw = record_raw
        self._static_sent = False

    def tap(self, device: str, url: str = ""):
        """A transport tap recording the raw bytes of ``device`` on /raw/<device>."""
        topic = f"/raw/{device}"

        def _tap(direction: str, host_time: float, data: bytes) -> None:
            if self.record_raw:
                ns = self.tb.ns(host_time)
                self.rec.write(topic, M.raw_bytes_msg(ns, device, direction, host_time, data, url), ns)
        return _tap

    def scan(self, scan: Scan) -> None:
        ns = self.tb.ns(scan.stamp)
        last = M.last_echo(scan)
        if last is not None:
            echo = Scan(stamp=scan.stamp, ranges=last[0], intensities=last[1], geometry=scan.geometry)
            self.rec.write("/scan" + M.LASTECHO_SUFFIX, M.laser_scan_msg(echo, ns, self.laser_frame), ns)
        self.rec.write("/scan", M.laser_scan_msg(scan, ns, self.laser_frame), ns)

    def odometry(self, odom: Odometry, msg=None) -> None:
        """Record /odom (``msg`` if given: the message already built by ``as_recorded_odometry``) and /tf."""
        ns = self.tb.ns(odom.stamp)
        if msg is None:
            msg = M.odometry_msg(odom, ns, self.odom_frame, self.base_frame)
        self.rec.write("/odom", msg, ns)
        tf = M.transform_stamped(ns, self.odom_frame, self.base_frame, odom.x, odom.y, odom.yaw)
        self.rec.write("/tf", M.tf_msg([tf]), ns)

    def cmd_vel(self, host_time: float, v: float, omega: float) -> None:
        ns = self.tb.ns(host_time)
        self.rec.write("/cmd_vel", M.twist_msg(v, omega), ns)

    def result(self, r: ScanResult) -> None:
        if r.estimate is None:
            return
        ns = self.tb.ns(r.scan.stamp)
        self.rec.write("/pose", M.pose_with_covariance_msg(r.estimate, ns, self.map_frame), ns)
        if r.corrected_pose is not None:
            self.rec.write("/pose/corrected", M.pose_with_covariance_msg(r.corrected_pose, ns, self.map_frame), ns)
        if r.p_glass is not None:
            self.rec.write("/glass/beams", M.laser_scan_msg(r.scan, ns, self.laser_frame, values=r.p_glass), ns)
        if r.odom is not None:
            map_odom = compose(r.estimate.pose, inverse(r.odom.pose))
            tf = M.transform_stamped(ns, self.map_frame, self.odom_frame, *map_odom)
            self.rec.write("/tf", M.tf_msg([tf]), ns)
        if not self._static_sent and r.laser_pose is not None:
            mount = compose(inverse(r.estimate.pose), r.laser_pose)
            tf = M.transform_stamped(ns, self.base_frame, self.laser_frame, *mount)
            self.rec.write("/tf_static", M.tf_msg([tf]), ns)
            self._static_sent = True

    def pose_graph(self, stamp_ns: int, snapshot) -> None:
        """/pose_graph/path (the optimised key-scan trajectory), /map/corrected and /glass/map/corrected (the
        maps re-integrated at it) of a :class:`~runtime.graph_worker.GraphSnapshot`, built here (see
        :meth:`cdr` for messages built elsewhere)."""
        from runtime.graph_worker import graph_messages

        self.cdr(stamp_ns, graph_messages(snapshot, stamp_ns, self.map_frame, self.tb))

    def cdr(self, stamp_ns: int, messages: list[tuple[str, bytes]]) -> None:
        """Messages serialised elsewhere, as (topic, CDR bytes)."""
        for topic, data in messages:
            self.rec.write(topic, data, stamp_ns)

    def maps(self, stamp_ns: int, occupancy_cdr: bytes, glass_cdr: bytes) -> None:
        """/map and /glass/map, serialised elsewhere (see :class:`runtime.map_worker.MapWorker`)."""
        self.rec.write("/map", occupancy_cdr, stamp_ns)
        self.rec.write("/glass/map", glass_cdr, stamp_ns)

    def summary(self, host_time: float, stats: dict) -> None:
        """A final /rosout line with the run's counters (JSON)."""
        ns = self.tb.ns(host_time)
        self.rec.write("/rosout", M.log_msg(ns, logging.INFO, "glassmap.runtime", "summary " + json.dumps(stats)),
                       ns)


def recording_metadata(time_base: M.TimeBase, **info: str) -> dict[str, dict[str, str]]:
    """The ``glassmap`` metadata record of a recording: clock offset, topics, settings (strings)."""
    meta = {"time_offset_ns": str(time_base.offset_ns), "scan_topic": "/scan", "odom_topic": "/odom"}
    meta.update({k: str(v) for k, v in info.items()})
    return {META_NAME: meta}


class RosoutHandler(logging.Handler):
    """A logging handler that records every log record on /rosout."""

    def __init__(self, recorder: McapRecorder, time_base: M.TimeBase, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.rec = recorder
        self.tb = time_base

    def emit(self, record: logging.LogRecord) -> None:
        try:
            import time

            ns = time.time_ns()
            self.rec.write("/rosout", M.log_msg(ns, record.levelno, record.name, record.getMessage(),
                                                record.pathname, record.funcName, record.lineno), ns)
        except Exception:
            self.handleError(record)
