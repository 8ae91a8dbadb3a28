"""ROS 2 message types and builders for the recording (rosbags type store, CDR serialisation).

The type store is ROS 2 Humble plus three foxglove_msgs types (``Grid`` and its parts, so that Foxglove
colours the glass confidence map) and one custom type, ``glassmap_msgs/msg/RawBytes``: the raw device bytes
of one read or write on a link, so a recording can be replayed through the real driver code.

Times: message stamps are wall-clock (``builtin_interfaces/Time``); the runtime keeps host monotonic times
and converts with a :class:`TimeBase`. Frames: ``map``, ``odom``, ``base_link``, ``laser``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from glassmap.types import LaserGeometry, Odometry, PoseEstimate, Scan

RAW_BYTES_TYPE = "glassmap_msgs/msg/RawBytes"
RAW_BYTES_MSG = """\
# Bytes seen on a device link in one read (rx, device -> host) or one write (tx, host -> device).
# header.stamp: wall-clock time the bytes were seen; header.frame_id: the device ("laser" or "base").
std_msgs/Header header
# "rx" (device -> host) or "tx" (host -> device)
string direction
# host monotonic clock (s) when the bytes were seen, for exact replay timing
float64 host_time
# the transport URL the bytes came from (tcp://..., serial://...)
string url
uint8[] data
"""

FOXGLOVE_TYPES = {
    "foxglove_msgs/msg/Vector2": "float64 x\nfloat64 y\n",
    "foxglove_msgs/msg/PackedElementField": (
        "uint8 UNKNOWN=0\nuint8 UINT8=1\nuint8 INT8=2\nuint8 UINT16=3\nuint8 INT16=4\nuint8 UINT32=5\n"
        "uint8 INT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 type\n"
    ),
    "foxglove_msgs/msg/Grid": (
        "builtin_interfaces/Time timestamp\nstring frame_id\ngeometry_msgs/Pose pose\nuint32 column_count\n"
        "foxglove_msgs/Vector2 cell_size\nuint32 row_stride\nuint32 cell_stride\n"
        "foxglove_msgs/PackedElementField[] fields\nuint8[] data\n"
    ),
}

# Topic -> message type of everything the runtime records.
TOPICS: dict[str, str] = {
    "/scan": "sensor_msgs/msg/LaserScan",
    "/scan/last_echo": "sensor_msgs/msg/LaserScan",  # multi-echo scans only (see LASTECHO_SUFFIX)
    "/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/glass/beams": "sensor_msgs/msg/LaserScan",
    "/map": "nav_msgs/msg/OccupancyGrid",
    "/glass/map": "foxglove_msgs/msg/Grid",
    "/rosout": "rcl_interfaces/msg/Log",
    "/cmd_vel": "geometry_msgs/msg/Twist",
    # with mapping.loop_closure: the pose corrected by the pose graph (per scan), the optimised key-scan
    # trajectory and the occupancy grid re-integrated at it (after each loop closure and at the end)
    "/pose/corrected": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/pose_graph/path": "nav_msgs/msg/Path",
    "/map/corrected": "nav_msgs/msg/OccupancyGrid",
    "/glass/map/corrected": "foxglove_msgs/msg/Grid",
    "/raw/laser": RAW_BYTES_TYPE,
    "/raw/base": RAW_BYTES_TYPE,
}


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Humble type store with the foxglove and glassmap types registered."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in FOXGLOVE_TYPES.items():
        types.update(get_types_from_msg(text, name))
    types.update(get_types_from_msg(RAW_BYTES_MSG, RAW_BYTES_TYPE))
    ts.register(types)
    return ts


def warm_up_serializers() -> None:
    """Build the type store and generate the CDR code of every recorded type now: generated at a type's first
    message instead, in the recorder's thread, it holds the GIL while the first scans wait."""
    ts = typestore()
    for name in sorted(set(TOPICS.values())):
        ts.get_msgdef(name)


def msgdef(msgtype: str) -> str:
    """The ``ros2msg`` schema text of a type, dependencies appended (the MCAP ROS 2 profile format)."""
    return typestore().generate_msgdef(msgtype, ros_version=2)[0]


@dataclass(frozen=True)
class TimeBase:
    """Maps host monotonic seconds to wall-clock nanoseconds (fixed offset taken once)."""

    offset_ns: int

    @classmethod
    def now(cls) -> TimeBase:
        return cls(time.time_ns() - int(time.monotonic() * 1e9))

    @classmethod
    def identity(cls) -> TimeBase:
        """Stamps are already wall seconds (replay of a recording)."""
        return cls(0)

    def ns(self, host_time: float) -> int:
        return int(round(host_time * 1e9)) + self.offset_ns

    def host(self, ns: int) -> float:
        return (ns - self.offset_ns) * 1e-9


def _T():
    return typestore().types


def stamp_msg(ns: int):
    return _T()["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header(ns: int, frame_id: str):
    return _T()["std_msgs/msg/Header"](stamp=stamp_msg(ns), frame_id=frame_id)


def quaternion(yaw: float):
    return _T()["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def yaw_of(q) -> float:
    """Yaw (rad) of a geometry_msgs/Quaternion (rotation about z; roll and pitch ignored)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def pose_msg(x: float, y: float, yaw: float):
    T = _T()
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                       orientation=quaternion(float(yaw)))


def pose_stamped_msg(x: float, y: float, yaw: float, ns: int, frame_id: str = "map"):
    return _T()["geometry_msgs/msg/PoseStamped"](header=header(ns, frame_id), pose=pose_msg(x, y, yaw))


def path_msg(stamps_ns: np.ndarray, poses: np.ndarray, ns: int, frame_id: str = "map"):
    """nav_msgs/Path of poses (N, 3) (x, y, yaw) stamped ``stamps_ns`` (N,)."""
    return _T()["nav_msgs/msg/Path"](header=header(ns, frame_id),
                                     poses=[pose_stamped_msg(*p, int(t), frame_id) for t, p in zip(stamps_ns, poses)])


_XY_YAW = np.ix_([0, 1, 5], [0, 1, 5])  # the (x, y, yaw) rows and columns of a 6x6 ROS covariance


def cov6(cov3: np.ndarray) -> np.ndarray:
    """3x3 covariance over (x, y, yaw) -> the row-major 6x6 ROS covariance over (x, y, z, roll, pitch, yaw)."""
    c = np.zeros((6, 6))
    c[_XY_YAW] = np.asarray(cov3, dtype=float)[:3, :3]
    return c.reshape(36)


def cov3(cov36) -> np.ndarray:
    c = np.asarray(cov36, dtype=float).reshape(6, 6)
    return c[_XY_YAW].copy()


def laser_scan_msg(scan: Scan, ns: int, frame_id: str = "laser", values: np.ndarray | None = None):
    """sensor_msgs/LaserScan of a scan (stamp = acquisition time of the first beam).

    ``values`` replaces the intensities (used for the per-beam glass probability topic).
    """
    g = scan.geometry
    n = scan.ranges.shape[0]
    inten = values if values is not None else scan.intensities
    return _T()["sensor_msgs/msg/LaserScan"](
        header=header(ns, frame_id),
        angle_min=float(g.angle_min),
        angle_max=float(g.angle_min + (n - 1) * g.angle_increment),
        angle_increment=float(g.angle_increment),
        time_increment=float(g.time_increment),
        scan_time=float(g.scan_time),
        range_min=float(g.range_min),
        range_max=float(g.range_max),
        ranges=np.asarray(scan.ranges, dtype=np.float32),
        intensities=np.asarray(inten, dtype=np.float32) if inten is not None else np.zeros(0, np.float32),
    )


def scan_from_msg(msg, stamp: float, seq: int = 0) -> Scan:
    """A Scan from a sensor_msgs/LaserScan (ROS 1 or 2); ``stamp`` in seconds (the caller's clock)."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    n = ranges.shape[0]
    geom = LaserGeometry(n_beams=n, angle_min=float(msg.angle_min), angle_increment=float(msg.angle_increment),
                         range_min=float(msg.range_min), range_max=float(msg.range_max),
                         scan_time=float(msg.scan_time) if msg.scan_time > 0 else 0.025)
    inten = np.asarray(msg.intensities, dtype=np.float64)
    return Scan(stamp=stamp, ranges=ranges, intensities=inten if inten.shape == ranges.shape else None,
                geometry=geom, seq=seq)


def odometry_msg(odom: Odometry, ns: int, frame_id: str = "odom", child_frame_id: str = "base_link"):
    T = _T()
    twist = T["geometry_msgs/msg/Twist"](
        linear=T["geometry_msgs/msg/Vector3"](x=float(odom.v), y=0.0, z=0.0),
        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=float(odom.omega)))
    return T["nav_msgs/msg/Odometry"](
        header=header(ns, frame_id), child_frame_id=child_frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(odom.x, odom.y, odom.yaw),
                                                       covariance=cov6(odom.covariance)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))


def odometry_from_msg(msg, stamp: float) -> Odometry:
    p = msg.pose.pose
    return Odometry(stamp=stamp, x=float(p.position.x), y=float(p.position.y), yaw=yaw_of(p.orientation),
                    v=float(msg.twist.twist.linear.x), omega=float(msg.twist.twist.angular.z),
                    covariance=cov3(msg.pose.covariance))


def pose_with_covariance_msg(est: PoseEstimate, ns: int, frame_id: str = "map"):
    T = _T()
    return T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=header(ns, frame_id),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(est.x, est.y, est.yaw),
                                                       covariance=cov6(est.covariance)))


def transform_stamped(ns: int, parent: str, child: str, x: float, y: float, yaw: float):
    T = _T()
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(ns, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=0.0),
            rotation=quaternion(float(yaw))))


def tf_msg(transforms: list):
    return _T()["tf2_msgs/msg/TFMessage"](transforms=transforms)


def twist_msg(v: float, omega: float):
    T = _T()
    return T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=float(v), y=0.0, z=0.0),
                                        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=float(omega)))


def occupancy_grid_msg(prob: np.ndarray, origin_xy: tuple[float, float], resolution: float, ns: int,
                       frame_id: str = "map"):
    """nav_msgs/OccupancyGrid from p(occupied) (H, W), row = y: 0..100, -1 where unknown (NaN or 0.5)."""
    p = np.asarray(prob)
    if p.dtype.kind != "f":
        p = p.astype(np.float64)
    data = np.full(p.size, -1, dtype=np.int8)
    # the known cells in float64, as a whole-map float64 pass would find them, at a fraction of its cost
    # (most of a map is unknown): the float32 pre-selection keeps every cell 1e-3 or more from 0.5
    flat = p.reshape(-1)
    with np.errstate(invalid="ignore"):
        cand = np.flatnonzero(np.abs(flat - np.asarray(0.5, dtype=flat.dtype)) > 0.9e-3)
    pk = flat[cand].astype(np.float64)
    keep = np.abs(pk - 0.5) > 1e-3
    data[cand[keep]] = np.clip(np.round(pk[keep] * 100), 0, 100).astype(np.int8)
    T = _T()
    info = T["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp_msg(ns), resolution=float(resolution), width=int(p.shape[1]), height=int(p.shape[0]),
        origin=pose_msg(origin_xy[0], origin_xy[1], 0.0))
    return T["nav_msgs/msg/OccupancyGrid"](header=header(ns, frame_id), info=info, data=data)


_GRID_CELL = np.dtype([("p_glass", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])


def glass_grid_msg(confidence: np.ndarray, origin_xy: tuple[float, float], resolution: float, ns: int,
                   frame_id: str = "map"):
    """foxglove_msgs/Grid of the glass confidence map: fields ``p_glass`` (float32, NaN off walls) and
    ``red``/``green``/``blue``/``alpha`` (uint8) in the paper's colours (blue not glass -> gray -> red glass;
    cells that are not walls transparent)."""
    c = np.asarray(confidence, dtype=np.float32)
    h, w = c.shape
    data = np.empty(h * w * 8, dtype=np.uint8)
    rec = data.view(_GRID_CELL)
    rec["p_glass"] = c.reshape(-1)
    rec["red"] = rec["green"] = rec["blue"] = 128  # what p = 0.5 gives: the colour of the transparent cells
    rec["alpha"] = 0
    known = np.flatnonzero(np.isfinite(rec["p_glass"]))  # the walls: a small share of the map
    pk = np.clip(rec["p_glass"][known], 0.0, 1.0)
    lo = pk < 0.5  # blue (0,0,255) -> gray (128,128,128) -> red (255,0,0)
    t = np.where(lo, pk / 0.5, (pk - 0.5) / 0.5)
    rec["red"][known] = np.where(lo, 128 * t, 128 + 127 * t).astype(np.uint8)
    rec["green"][known] = np.where(lo, 128 * t, 128 * (1 - t)).astype(np.uint8)
    rec["blue"][known] = np.where(lo, 255 - 127 * t, 128 * (1 - t)).astype(np.uint8)
    rec["alpha"][known] = 255
    T = _T()
    F = T["foxglove_msgs/msg/PackedElementField"]
    fields = [F(name="p_glass", offset=0, type=7), F(name="red", offset=4, type=1),
              F(name="green", offset=5, type=1), F(name="blue", offset=6, type=1), F(name="alpha", offset=7, type=1)]
    return T["foxglove_msgs/msg/Grid"](
        timestamp=stamp_msg(ns), frame_id=frame_id, pose=pose_msg(origin_xy[0], origin_xy[1], 0.0),
        column_count=int(w), cell_size=T["foxglove_msgs/msg/Vector2"](x=float(resolution), y=float(resolution)),
        row_stride=int(w * 8), cell_stride=8, fields=fields, data=data)


def grid_values(msg, field: str = "p_glass") -> np.ndarray:
    """Decode one float32 field of a foxglove_msgs/Grid back into an (H, W) array."""
    f = next(f for f in msg.fields if f.name == field)
    raw = np.asarray(msg.data, dtype=np.uint8)
    h = raw.size // msg.row_stride
    rows = raw.reshape(h, msg.row_stride)[:, : msg.column_count * msg.cell_stride]
    cells = rows.reshape(h, msg.column_count, msg.cell_stride)[:, :, f.offset: f.offset + 4]
    return np.ascontiguousarray(cells).view("<f4")[:, :, 0]


LOG_LEVELS = {10: 10, 20: 20, 30: 30, 40: 40, 50: 50}


def log_msg(ns: int, level: int, name: str, text: str, file: str = "", function: str = "", line: int = 0):
    """rcl_interfaces/Log (level: Python logging levels map 1:1 onto the ROS 2 levels 10..50)."""
    lvl = max(10, min(50, (int(level) // 10) * 10))
    return _T()["rcl_interfaces/msg/Log"](stamp=stamp_msg(ns), level=lvl, name=name, msg=text, file=file,
                                          function=function, line=int(line))


def raw_bytes_msg(ns: int, device: str, direction: str, host_time: float, data: bytes, url: str = ""):
    return _T()[RAW_BYTES_TYPE](header=header(ns, device), direction=direction, host_time=float(host_time),
                                url=url, data=np.frombuffer(bytes(data), dtype=np.uint8).copy())


def as_recorded_scan(scan: Scan, tb: TimeBase) -> Scan:
    """The scan exactly as a replay of the recording will see it (float32 ranges, intensities and geometry,
    stamp through nanoseconds). The runtime processes this form, so replays reproduce its maps exactly."""
    g = scan.geometry
    f = np.float32
    geom = LaserGeometry(n_beams=scan.ranges.shape[0], angle_min=float(f(g.angle_min)),
                         angle_increment=float(f(g.angle_increment)), range_min=float(f(g.range_min)),
                         range_max=float(f(g.range_max)),
                         scan_time=float(f(g.scan_time)) if f(g.scan_time) > 0 else 0.025)
    inten = None if scan.intensities is None else scan.intensities.astype(np.float32).astype(np.float64)
    if scan.echoes is None:
        ranges, echoes, echo_i = scan.ranges.astype(np.float32).astype(np.float64), None, None
    else:  # recorded as the last echo only (LASTECHO_SUFFIX), so keep only that
        from runtime.messages_jit import recorded_last_echoes

        ranges, echoes, echo_i = recorded_last_echoes(*_echo_arrays(scan))
    return Scan(stamp=tb.host(tb.ns(scan.stamp)), ranges=ranges, intensities=inten, geometry=geom,
                sensor_stamp=scan.sensor_stamp, seq=scan.seq, echoes=echoes, echo_intensities=echo_i)


LASTECHO_SUFFIX = "/last_echo"
"""A multi-echo scan is recorded as two LaserScan messages with the same stamp: the first echo on the scan
topic and, just before it, the last echo on ``<scan topic>/last_echo`` (range NaN and intensity 0 where
a beam had one echo)."""


def last_echo(scan: Scan) -> tuple[np.ndarray, np.ndarray] | None:
    """(ranges (n,) m, intensities (n,)) of each beam's last echo beyond the first (NaN / 0 where it had one
    echo), or None for a single-echo scan. ``scan.echoes`` may hold [first, last] (simulator) or the
    further echoes (Hokuyo client): the last finite column that differs from the first echo."""
    if scan.echoes is None:
        return None
    from runtime.messages_jit import last_echoes

    return last_echoes(*_echo_arrays(scan))


def _echo_arrays(scan: Scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' inputs of a scan with echoes: ranges (n,), echoes (n, k), their intensities (n, k) (0
    without), float64 and contiguous."""
    r = np.ascontiguousarray(scan.ranges, dtype=np.float64)
    e = np.ascontiguousarray(scan.echoes, dtype=np.float64).reshape(r.shape[0], -1)
    ei = (np.zeros_like(e) if scan.echo_intensities is None
          else np.ascontiguousarray(scan.echo_intensities, dtype=np.float64).reshape(r.shape[0], -1))
    return r, e, ei


def as_recorded_odometry(odom: Odometry, tb: TimeBase, frame_id: str = "odom",
                         child_frame_id: str = "base_link") -> tuple[Odometry, object]:
    """The odometry exactly as a replay of the recording will see it, and the nav_msgs/Odometry to record:
    the message is built once and decoded back (yaw through its quaternion, stamp through nanoseconds), so
    live processing and replay get bit-identical values."""
    ns = tb.ns(odom.stamp)
    msg = odometry_msg(odom, ns, frame_id, child_frame_id)
    return odometry_from_msg(msg, tb.host(ns)), msg
