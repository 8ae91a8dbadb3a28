"""Readers for replay: glassmap MCAP recordings, other ROS 2 MCAP files, ROS 2 bags and ROS 1 bags.

Every reader yields the same things in time order: :class:`glassmap.types.Scan` (laser frame) and
:class:`glassmap.types.Odometry` (odom frame), stamped in seconds. glassmap recordings give back the exact
host monotonic stamps of the live run (the recording stores the clock offset); other files give their
header stamps in seconds. Odometry comes from nav_msgs/Odometry, or else from /tf ``odom -> base`` transforms.
Raw device bytes (glassmap recordings only) come out chunk by chunk through :func:`iter_raw_chunks`, or as
:class:`drivers.capture.Capture` objects through :func:`read_captures`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.records import Metadata
from mcap.stream_reader import StreamReader

from drivers.capture import Capture, Chunk
from glassmap.types import Odometry, Scan
from runtime.messages import (
    LASTECHO_SUFFIX,
    RAW_BYTES_TYPE,
    TimeBase,
    odometry_from_msg,
    scan_from_msg,
    stamp_to_ns,
    typestore,
    yaw_of,
)
from runtime.inputs import InputError
from runtime.mcap_walk import iter_channel_messages
from runtime.raw_cdr import raw_bytes_fields
from runtime.recorder import iter_mcap_raw

log = logging.getLogger(__name__)

META_NAME = "glassmap"
BASE_FRAMES = ("base_link", "base_footprint", "base")


class ReplayInputError(InputError):
    """A file cannot be replayed: missing, unknown kind, or without laser scans."""


def read_metadata(path: str | Path) -> dict[str, str]:
    """The ``glassmap`` metadata record of a recording ({} if absent); read from the file's start."""
    try:
        with open(path, "rb") as f:
            for rec in StreamReader(f).records:
                if isinstance(rec, Metadata) and rec.name == META_NAME:
                    return dict(rec.metadata)
    except Exception:  # cut-short file: metadata is written first, so anything later does not matter
        pass
    return {}


def recording_kind(path: Path) -> str:
    """'mcap', 'rosbag1' or 'rosbag2' from the path (ReplayInputError if it is none of them or missing)."""
    if not path.exists():
        raise ReplayInputError(f"{path}: no such file or directory")
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return "rosbag2"
        raise ReplayInputError(f"{path}: a directory without metadata.yaml is not a ROS 2 bag")
    if path.suffix == ".bag":
        return "rosbag1"
    if path.suffix == ".mcap":
        return "mcap"
    if path.suffix == ".db3":
        return "rosbag2"
    raise ReplayInputError(f"{path}: unknown file kind (expected .mcap, .bag, .db3 or a ROS 2 bag directory)")


def iter_messages(path: str | Path, *, scan_topic: str | None = None,
                  odom_topic: str | None = None) -> Iterator[Scan | Odometry]:
    """Scans and odometry of a recording or bag in file time order (see module docstring)."""
    path = Path(path)
    kind = recording_kind(path)
    if kind == "mcap":
        yield from _iter_mcap(path, scan_topic, odom_topic)
    else:
        yield from _iter_anyreader(path, scan_topic, odom_topic)


def _iter_mcap(path: Path, scan_topic: str | None, odom_topic: str | None) -> Iterator[Scan | Odometry]:
    meta = read_metadata(path)
    tb = TimeBase(int(meta["time_offset_ns"])) if "time_offset_ns" in meta else TimeBase.identity()
    scan_topic = scan_topic or meta.get("scan_topic", "/scan")
    odom_topic = odom_topic or meta.get("odom_topic", "/odom")
    ts = typestore()
    seen_scan = False
    have_odom = False
    echo_topic = scan_topic + LASTECHO_SUFFIX
    pending_echo = None  # (stamp ns, last-echo LaserScan) waiting for its first-echo scan
    seq = 0  # scans numbered in recording order (LaserScan has no sequence number), as in the log lines
    for r in iter_mcap_raw(path):
        if r.topic == echo_topic and r.msgtype.endswith("LaserScan"):
            msg = ts.deserialize_cdr(r.data, r.msgtype)
            pending_echo = (stamp_to_ns(msg.header.stamp), msg)
        elif r.topic == scan_topic and r.msgtype.endswith("LaserScan"):
            msg = ts.deserialize_cdr(r.data, r.msgtype)
            seen_scan = True
            ns = stamp_to_ns(msg.header.stamp)
            seq += 1
            scan = scan_from_msg(msg, tb.host(ns), seq=seq)
            if pending_echo is not None and pending_echo[0] == ns:
                er = np.asarray(pending_echo[1].ranges, dtype=np.float64)
                ei = np.asarray(pending_echo[1].intensities, dtype=np.float64)
                if er.shape == scan.ranges.shape:
                    scan.echoes = er[:, None]
                    scan.echo_intensities = (ei if ei.shape == er.shape else np.zeros_like(er))[:, None]
            pending_echo = None
            yield scan
        elif r.topic == odom_topic and r.msgtype == "nav_msgs/msg/Odometry":
            msg = ts.deserialize_cdr(r.data, r.msgtype)
            have_odom = True
            yield odometry_from_msg(msg, tb.host(stamp_to_ns(msg.header.stamp)))
        elif r.topic == "/tf" and not have_odom and r.msgtype == "tf2_msgs/msg/TFMessage":
            msg = ts.deserialize_cdr(r.data, r.msgtype)
            yield from _odom_from_tf(msg, tb)
    if not seen_scan:
        raise ReplayInputError(f"{path}: no sensor_msgs/LaserScan messages on {scan_topic}")


def _odom_from_tf(msg, tb: TimeBase) -> Iterator[Odometry]:
    for t in msg.transforms:
        parent = t.header.frame_id.lstrip("/")
        child = t.child_frame_id.lstrip("/")
        if parent == "odom" and child in BASE_FRAMES:
            tr = t.transform
            yield Odometry(stamp=tb.host(stamp_to_ns(t.header.stamp)), x=float(tr.translation.x),
                           y=float(tr.translation.y), yaw=yaw_of(tr.rotation))


def _iter_anyreader(path: Path, scan_topic: str | None, odom_topic: str | None) -> Iterator[Scan | Odometry]:
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, Exception) as exc:
        raise ReplayInputError(f"{path}: cannot open as a ROS bag ({exc})") from exc
    tb = TimeBase.identity()
    try:
        conns = reader.connections
        scans = [c for c in conns if c.msgtype.endswith("LaserScan") and (scan_topic in (None, c.topic))]
        if not scans:
            raise ReplayInputError(f"{path}: no sensor_msgs/LaserScan topic"
                                   + (f" named {scan_topic}" if scan_topic else ""))
        odoms = [c for c in conns if c.msgtype.split("/")[-1] == "Odometry" and (odom_topic in (None, c.topic))]
        tfs = [c for c in conns if c.topic in ("/tf", "tf") and c.msgtype.split("/")[-1] == "TFMessage"]
        scan_t = scans[0].topic
        selected = [c for c in scans if c.topic == scan_t]
        if odoms:
            selected += [c for c in odoms if c.topic == odoms[0].topic]
        else:
            selected += tfs
        if not odoms and not tfs:
            log.warning("%s: no odometry and no /tf: the pose comes from scan matching alone", path)
        seq = 0
        for con, _t, raw in reader.messages(connections=selected):
            msg = reader.deserialize(raw, con.msgtype)
            kind = con.msgtype.split("/")[-1]
            if kind == "LaserScan":
                seq += 1
                yield scan_from_msg(msg, tb.host(stamp_to_ns(msg.header.stamp)), seq=seq)
            elif kind == "Odometry":
                yield odometry_from_msg(msg, tb.host(stamp_to_ns(msg.header.stamp)))
            else:
                yield from _odom_from_tf(msg, tb)
    finally:
        reader.close()


@dataclass(frozen=True)
class RawChunk:
    """One recorded read or write of a device link: ``device`` ('laser', 'base'), ``host_time`` (s, the live
    run's host clock), ``direction`` ('tx' host -> device, 'rx' device -> host), ``url`` of the link, ``data``."""

    device: str
    host_time: float
    direction: str
    url: str
    data: bytes


def _is_raw(topic: str, msgtype: str) -> bool:
    return msgtype == RAW_BYTES_TYPE


def iter_raw_chunks(path: str | Path) -> Iterator[RawChunk]:
    """The raw device bytes of a glassmap recording (/raw/* messages), one chunk at a time in file order.

    Only the RawBytes messages are read out of the file (:mod:`runtime.mcap_walk`) and decoded
    (:mod:`runtime.raw_cdr`; rosbags' deserialiser for what that does not decode)."""
    ts = typestore()
    for r in iter_channel_messages(path, _is_raw):
        fields = raw_bytes_fields(r.data, ts.max_sequence_length)
        if fields is None:
            msg = ts.deserialize_cdr(r.data, r.msgtype)
            fields = (msg.header.frame_id, msg.host_time, msg.direction, msg.url, bytes(msg.data))
        yield RawChunk(*fields)


def read_captures(path: str | Path) -> dict[str, Capture]:
    """The raw device bytes of a glassmap recording as captures, by device ('laser', 'base'); all in memory
    (a replay streams them instead: :func:`iter_raw_chunks`).

    Chunk times are seconds since the device's first chunk (the capture format); the absolute host time
    of the first chunk is in ``capture.note`` as JSON ``{"t0": host_seconds, "url": ...}``.
    """
    caps: dict[str, Capture] = {}
    t0: dict[str, float] = {}
    for c in iter_raw_chunks(path):
        if c.device not in caps:
            caps[c.device] = Capture(device=c.device, note=json.dumps({"t0": c.host_time, "url": c.url}))
            t0[c.device] = c.host_time
        caps[c.device].chunks.append(Chunk(c.host_time - t0[c.device], c.direction, c.data))
    return caps
