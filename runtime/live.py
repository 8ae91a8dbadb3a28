"""Live view: the recording's topics served over the Foxglove WebSocket protocol (``--live [HOST:]PORT``).

:class:`LiveView` has the producer interface of :class:`runtime.recorder.McapRecorder` (``write(topic, msg,
log_ns)``), so :class:`runtime.sink.RecordingSink` feeds it the very messages it records, through
:class:`Fanout`. The protocol itself is the ``foxglove-sdk`` package's server (Foxglove's implementation);
this module only queues, serialises (the recorder's type store and ``ros2msg`` schemas, CDR) and logs.

Never slows the runtime: ``write`` is a non-blocking put on a bounded queue (full: the message is dropped
and counted); serialisation and logging run in one thread; the SDK server keeps a bounded backlog per
client and drops that client's oldest messages when it does not read. ``/map`` and ``/glass/map`` are
throttled to one message each per ``map_period`` seconds (host clock); the raw device bytes are not served.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

from runtime.messages import TOPICS, msgdef, typestore
from runtime.output_args import LiveViewError, parse_address

log = logging.getLogger(__name__)

# The recording's topics that are served live (everything but the raw device bytes).
LIVE_TOPICS: dict[str, str] = {t: ty for t, ty in TOPICS.items() if not t.startswith("/raw/")}
MAP_TOPICS = frozenset({"/map", "/glass/map"})
_STOP = object()


@dataclass
class LiveStats:
    """Counters of the live view: messages logged to the server, dropped (queue full), maps throttled."""

    sent: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)
    throttled: int = 0
    errors: int = 0

    @property
    def total_sent(self) -> int:
        return sum(self.sent.values())

    @property
    def total_dropped(self) -> int:
        return sum(self.dropped.values())


class LiveView:
    """A Foxglove WebSocket server publishing the runtime's messages (ROS 2 CDR, ``ros2msg`` schemas).

    host, port: where to listen (loopback by default; port 0 = any free port, see :attr:`port`).
    map_period: minimum seconds between two /map (and two /glass/map) messages.
    queue_size: messages waiting for serialisation; when full, new messages are dropped and counted.
    backlog: messages the server buffers per client before dropping that client's oldest.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, map_period: float = 1.0,
                 queue_size: int = 256, backlog: int = 256, topics: dict[str, str] | None = None) -> None:
        try:
            import foxglove
            from foxglove import Channel, Context, Schema
        except ImportError as exc:
            raise LiveViewError(f"the live view needs the foxglove-sdk package ({exc}): "
                                "pip install foxglove-sdk") from exc
        if map_period < 0 or queue_size < 1 or backlog < 1:
            raise ValueError("map_period must be >= 0, queue_size and backlog >= 1")
        self.topics = dict(LIVE_TOPICS if topics is None else topics)
        self.map_period = map_period
        self.stats = LiveStats()
        self._last_map: dict[str, float] = {}
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._closed = False
        self._ctx = Context()
        # a viewer closing its tab is normal: the SDK's per-client connection errors are not the operator's
        logging.getLogger("foxglove.websocket.connected_client").setLevel(logging.CRITICAL)
        try:
            self._server = foxglove.start_server(name="glassmap", host=host, port=port, context=self._ctx,
                                                 message_backlog_size=backlog)
        except Exception as exc:  # the SDK raises RuntimeError with the OS reason
            raise LiveViewError(f"cannot serve the live view on {host}:{port}: {exc}") from exc
        self.host = host
        self._channels = {}
        for topic, msgtype in self.topics.items():
            schema = Schema(name=msgtype, encoding="ros2msg", data=msgdef(msgtype).encode("utf-8"))
            self._channels[topic] = Channel(topic, schema=schema, message_encoding="cdr", context=self._ctx)
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self._server.port

    @property
    def url(self) -> str:
        """The WebSocket URL to open in Foxglove (Open connection -> Foxglove WebSocket)."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"ws://{host}:{self.port}"

    def app_url(self) -> str | None:
        """A https://app.foxglove.dev link that opens this server as the data source."""
        return self._server.app_url()

    # -- producer side (any thread) ---------------------------------------------------------------------
    def write(self, topic: str, msg, log_ns: int, publish_ns: int | None = None) -> bool:
        """Queue one message (object, zero-argument callable, or CDR bytes) like
        :meth:`McapRecorder.write`. Returns False if it was not queued (topic not served, map throttled,
        queue full: counted in ``stats.dropped``, or closed)."""
        if self._closed or topic not in self._channels:
            return False
        if topic in MAP_TOPICS and self.map_period > 0:
            now = time.monotonic()
            if now - self._last_map.get(topic, -float("inf")) < self.map_period:
                self.stats.throttled += 1
                return False
            self._last_map[topic] = now
        try:
            self._queue.put_nowait((topic, msg, int(log_ns)))
            return True
        except queue.Full:
            self.stats.dropped[topic] += 1
            return False

    def close(self, timeout: float = 5.0) -> None:
        """Send what is queued (for at most ``timeout`` s), then stop the thread and the server. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._queue.put(_STOP, timeout=timeout)
        except queue.Full:
            log.error("live view: sending thread stuck; %d messages not sent", self._queue.qsize())
        self._thread.join(timeout)
        # The SDK's stop() waits for every client's pending sends: a viewer that stopped reading would hold
        # it (and us) for ever, so it runs in a daemon thread and we wait for it a bounded time.
        stopper = threading.Thread(target=self._server.stop, name="live-view-stop", daemon=True)
        stopper.start()
        stopper.join(min(timeout, 2.0))
        if stopper.is_alive():
            log.warning("live view: a viewer is not reading; the server is left to stop when the process ends")

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- serialising thread -------------------------------------------------------------------------------
    def _run(self) -> None:
        ts = typestore()
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            topic, msg, log_ns = item
            try:
                if callable(msg):
                    msg = msg()
                data = msg if isinstance(msg, bytes) else bytes(ts.serialize_cdr(msg, self.topics[topic]))
                self._channels[topic].log(data, log_time=log_ns)
                self.stats.sent[topic] += 1
            except Exception as exc:  # a bad message must not stop the live view
                self.stats.errors += 1
                log.warning("live view: message on %s not sent: %s", topic, exc)


class Fanout:
    """The producer interface of a recorder (``write``) feeding several: the MCAP recorder and the live
    view get the same message objects."""

    def __init__(self, *targets) -> None:
        self.targets = [t for t in targets if t is not None]

    def write(self, topic: str, msg, log_ns: int, publish_ns: int | None = None) -> bool:
        ok = False
        for t in self.targets:
            ok = t.write(topic, msg, log_ns, publish_ns) or ok
        return ok


def start_live_view(output) -> LiveView:
    """The live view of an :class:`runtime.config.OutputConfig` (``live``, ``live_map_period``,
    ``live_queue_size``)."""
    host, port = parse_address(output.live)
    return LiveView(host, port, map_period=output.live_map_period, queue_size=output.live_queue_size)


class ReplayPublisher:
    """Publishes a replay to a :class:`LiveView` as the live run would: /scan, /odom + /tf, /pose,
    /glass/beams, and the maps every ``map_period`` seconds (wall clock) from a copy made between scans.

    time_base: host seconds of the replayed stamps -> wall-clock ns (the recording's clock offset)."""

    def __init__(self, live: LiveView, time_base, *, map_frame: str = "map", laser_frame: str = "laser",
                 base_frame: str = "base_link", odom_frame: str = "odom", map_period: float = 1.0) -> None:
        from runtime.sink import RecordingSink

        self.live = live
        self.tb = time_base
        self.map_frame = map_frame
        self.map_period = map_period
        self.sink = RecordingSink(live, time_base, laser_frame=laser_frame, base_frame=base_frame,
                                  odom_frame=odom_frame, map_frame=map_frame, record_raw=False)
        self._next_map = 0.0

    def publish(self, odometry: list, result, processor) -> None:
        """One processed scan: the odometry that preceded it, its :class:`ScanResult`, and the processor
        (for the maps)."""
        for odom in odometry:
            self.sink.odometry(odom)
        self.sink.scan(result.scan)
        self.sink.result(result)
        now = time.monotonic()
        if now >= self._next_map:
            self._next_map = now + self.map_period
            self.publish_maps(processor, result.scan.stamp)

    def publish_maps(self, processor, stamp: float) -> None:
        from runtime.map_worker import map_messages

        ns = self.tb.ns(stamp)
        self.sink.maps(ns, *map_messages(processor.copy_maps(), ns, self.map_frame))
