"""MCAP recorder (ROS 2 profile: CDR messages, ros2msg schemas) writing from its own thread.

The event loop only builds message objects and puts them on a bounded queue (:meth:`McapRecorder.write`,
never blocks); the writer thread serialises them with the rosbags type store, writes them with the ``mcap``
library and compresses chunks. A chunk is closed when it exceeds ``chunk_size`` bytes or is older than
``chunk_interval`` seconds, and is flushed to the OS at once: if the process is killed (SIGKILL, power
loss of the laptop's disk cache aside) everything up to the last completed chunk is in the file. Such a
file has no summary and footer; :func:`read_mcap` reads it anyway and :func:`recover_mcap` rewrites it into
a complete file (for Foxglove and rosbags' AnyReader).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from runtime.messages import TOPICS, msgdef, typestore

log = logging.getLogger(__name__)

PROFILE = "ros2"
_STOP = object()


class RecorderError(Exception):
    """The recording cannot be written (disk full, permission, bad path)."""


@dataclass
class RecorderStats:
    """Counters of the recorder (messages per topic written, dropped because the queue was full)."""

    written: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)
    chunks_flushed: int = 0
    errors: int = 0

    @property
    def total_written(self) -> int:
        return sum(self.written.values())

    @property
    def total_dropped(self) -> int:
        return sum(self.dropped.values())


class McapRecorder:
    """Record ROS 2 messages to an MCAP file from a writer thread.

    ``write(topic, msg, log_ns)`` is thread-safe and non-blocking: when the queue is full the message is
    dropped and counted in ``stats.dropped`` (never silently). ``close()`` drains the queue, writes the
    summary and footer. Topic types come from :data:`runtime.messages.TOPICS` unless given explicitly.
    """

    def __init__(self, path: str | Path, *, chunk_size: int = 512 * 1024, chunk_interval: float = 1.0,
                 compression: str = "zstd", queue_size: int = 20000,
                 topics: dict[str, str] | None = None,
                 metadata: dict[str, dict[str, str]] | None = None) -> None:
        if chunk_size <= 0 or chunk_interval <= 0:
            raise ValueError("chunk_size and chunk_interval must be positive")
        try:
            comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
                compression]
        except KeyError:
            raise ValueError(f"compression must be zstd, lz4 or none, got {compression!r}") from None
        self.path = Path(path)
        self.chunk_interval = chunk_interval
        self.topics = dict(TOPICS if topics is None else topics)
        self.stats = RecorderStats()
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise RecorderError(f"cannot create recording {self.path}: {exc.strerror or exc}") from exc
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile=PROFILE, library="glassmap")
        for name, values in (metadata or {}).items():  # written first: survives a crash
            self._writer.add_metadata(name, {k: str(v) for k, v in values.items()})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    # -- producer side (any thread) ---------------------------------------------------------------------
    def write(self, topic: str, msg, log_ns: int, publish_ns: int | None = None) -> bool:
        """Queue one message; returns False (and counts it) if the queue is full or the recorder closed.

        ``msg`` may be a zero-argument callable returning the message: it is then built in the writer thread
        (so the caller does not pay for it); or ``bytes``: the message already serialised as CDR."""
        if self._closed:
            self.stats.dropped[topic] += 1
            return False
        try:
            self._queue.put_nowait((topic, msg, int(log_ns), int(publish_ns if publish_ns is not None else log_ns)))
            return True
        except queue.Full:
            self.stats.dropped[topic] += 1
            return False

    @property
    def backlog(self) -> int:
        return self._queue.qsize()

    @property
    def error(self) -> BaseException | None:
        """The exception that stopped the writer thread, if any."""
        return self._error

    def close(self, timeout: float = 30.0) -> None:
        """Write everything queued, then the summary and footer. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.error("recorder: writer thread did not finish within %.0f s; %s may lack its footer",
                      timeout, self.path)
            return
        try:
            if self._error is None:
                self._writer.finish()
            self._file.close()
        except OSError as exc:
            raise RecorderError(f"cannot finish recording {self.path}: {exc.strerror or exc}") from exc
        if self._error is not None:
            raise RecorderError(f"recording {self.path} stopped early: {self._error}") from self._error

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- writer thread ------------------------------------------------------------------------------------
    def _channel(self, topic: str) -> int:
        cid = self._channels.get(topic)
        if cid is not None:
            return cid
        msgtype = self.topics.get(topic)
        if msgtype is None:
            raise ValueError(f"recorder: unknown topic {topic!r} (add it to the recorder's topics)")
        sid = self._schemas.get(msgtype)
        if sid is None:
            sid = self._writer.register_schema(name=msgtype, encoding="ros2msg",
                                               data=msgdef(msgtype).encode("utf-8"))
            self._schemas[msgtype] = sid
        cid = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
        self._channels[topic] = cid
        return cid

    def _run(self) -> None:
        ts = typestore()
        last_flush = time.monotonic()
        dirty = False
        while True:
            timeout = max(0.0, self.chunk_interval - (time.monotonic() - last_flush))
            try:
                item = self._queue.get(timeout=timeout if dirty else None)
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            try:
                if item is not None:
                    topic, msg, log_ns, pub_ns = item
                    cid = self._channel(topic)
                    if callable(msg):
                        msg = msg()
                    data = msg if isinstance(msg, bytes) else ts.serialize_cdr(msg, self.topics[topic])
                    self._writer.add_message(channel_id=cid, log_time=log_ns, publish_time=pub_ns,
                                             data=bytes(data), sequence=self.stats.written[topic])
                    self.stats.written[topic] += 1
                    dirty = True
                if dirty and time.monotonic() - last_flush >= self.chunk_interval:
                    self._writer.flush()  # closes the chunk and flushes the file
                    self.stats.chunks_flushed += 1
                    last_flush = time.monotonic()
                    dirty = False
            except OSError as exc:
                self._error = exc
                log.error("recorder: writing %s failed (%s); recording stopped", self.path, exc)
                self._drain()
                return
            except Exception as exc:  # a bad message must not kill the recording
                self.stats.errors += 1
                log.warning("recorder: message on %s not recorded: %s", item[0] if item else "?", exc)

    def _drain(self) -> None:
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP:
                self.stats.dropped[item[0]] += 1


# -- reading -----------------------------------------------------------------------------------------------
@dataclass
class McapRecord:
    topic: str
    msgtype: str
    log_ns: int
    data: bytes


def iter_mcap_raw(path: str | Path) -> Iterator[McapRecord]:
    """Every message of an MCAP file in file order, also from a file cut short (a crash or SIGKILL):
    reading stops quietly at the first incomplete record (the tail after the last completed chunk)."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False)
        it = reader.records
        while True:
            try:
                rec = next(it)
            except StopIteration:
                return
            except (McapError, EOFError, ValueError, IndexError, OSError) as exc:
                log.info("%s: stopped reading at an incomplete record (%s)", path, type(exc).__name__)
                return
            except Exception as exc:  # struct.error, zstd errors on a truncated chunk
                log.info("%s: stopped reading at a damaged record (%s)", path, exc)
                return
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None:
                    continue
                sc = schemas.get(ch.schema_id)
                yield McapRecord(ch.topic, sc.name if sc else "", rec.log_time, rec.data)


def read_mcap(path: str | Path, topics: set[str] | None = None) -> Iterator[tuple[str, str, int, object]]:
    """Decoded messages ``(topic, msgtype, log_ns, msg)`` of a glassmap recording (complete or cut short).

    Types are decoded with the glassmap type store (ROS 2 Humble + foxglove + glassmap_msgs)."""
    ts = typestore()
    for r in iter_mcap_raw(path):
        if topics is not None and r.topic not in topics:
            continue
        if r.msgtype not in ts.types:
            continue
        yield r.topic, r.msgtype, r.log_ns, ts.deserialize_cdr(r.data, r.msgtype)


@dataclass
class RecoverReport:
    messages: int
    topics: dict[str, int]


def recover_mcap(src: str | Path, dst: str | Path, *, compression: str = "zstd") -> RecoverReport:
    """Rewrite a recording cut short by a crash into a complete MCAP file (summary, index, footer)."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    new_schema: dict[int, int] = {}
    new_channel: dict[int, int] = {}
    counts: Counter = Counter()
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
    with open(dst, "wb") as out:
        w = Writer(out, compression=comp)
        w.start(profile=PROFILE, library="glassmap-recover")
        with open(src, "rb") as f:
            it = StreamReader(f).records
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    break
                except Exception:  # the damaged tail
                    break
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Metadata):  # the recording's settings and clock offset
                    w.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    ch = channels[rec.channel_id]
                    if ch.schema_id not in new_schema:
                        s = schemas[ch.schema_id]
                        new_schema[ch.schema_id] = w.register_schema(s.name, s.encoding, s.data)
                    if ch.id not in new_channel:
                        new_channel[ch.id] = w.register_channel(ch.topic, ch.message_encoding,
                                                                new_schema[ch.schema_id], ch.metadata)
                    w.add_message(new_channel[ch.id], rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    counts[ch.topic] += 1
        w.finish()
    return RecoverReport(messages=sum(counts.values()), topics=dict(counts))
