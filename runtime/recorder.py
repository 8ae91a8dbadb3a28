"""MCAP recorder (ROS 2 profile: CDR messages, ros2msg schemas) writing from its own thread.

The event loop only builds message objects and puts them on a bounded queue (:meth:`McapRecorder.write`,
never blocks); the writer thread serialises them with the rosbags type store, writes them with the ``mcap``
library and compresses chunks. A chunk is closed when it exceeds ``chunk_size`` bytes or is older than
``chunk_interval`` seconds, and is flushed to the OS at once: if the process is killed (SIGKILL, power
loss of the laptop's disk cache aside) everything up to the last completed chunk is in the file. Such a
file has no summary and footer; :func:`read_mcap` reads it anyway and :func:`recover_mcap` rewrites it into
a complete file (for Foxglove and rosbags' AnyReader). A message larger than ``chunk_size`` (a map) gets a
chunk of its own, which a reader of the other channels (a raw replay, :mod:`runtime.mcap_walk`) skips
without decompressing it.

Splits (long field sessions): with ``split_size`` (bytes) and/or ``split_duration`` (s) the recording is a
series of complete files ``<stem>_0000.mcap``, ``<stem>_0001.mcap``, ... (names sort in time order). The
writer thread closes a file (summary, footer) once it holds ``split_size`` bytes (checked after each chunk,
so a file can exceed it by up to one chunk) or has been open ``split_duration`` seconds, and writes the next
message into the next file: nothing is lost or repeated at a boundary. Each file carries the metadata and
starts with the latest ``/tf_static``, so each one opens on its own in Foxglove and replays on its own.

A write error (disk full, a file-size limit) stops the recording, not the runtime: one error message, the
messages after it are dropped and counted, what was written stays readable (:func:`read_mcap`, or
:func:`recover_mcap` to add the footer).
"""

from __future__ import annotations

import errno
import itertools
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
# The writer thread takes what is queued, then sleeps this long (s) before it waits for more: one wake-up per
# period instead of one per message (~7 per scan), each of which would take the GIL from the processing thread.
WAKE_PERIOD = 0.05
# Topics whose latest message starts every split file (latched, as in ROS).
LATCHED_TOPICS = frozenset({"/tf_static"})


class RecorderError(Exception):
    """The recording cannot be written (disk full, permission, bad path)."""


@dataclass
class RecorderStats:
    """Counters of the recorder (messages per topic written, dropped because the queue was full)."""

    written: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)
    chunks_flushed: int = 0
    errors: int = 0
    files: list[str] = field(default_factory=list)  # files written, in order (one unless split)
    stopped: str = ""  # why the recording stopped early (a write error), "" if it did not

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
                 metadata: dict[str, dict[str, str]] | None = None,
                 split_size: int = 0, split_duration: float = 0.0) -> None:
        if chunk_size <= 0 or chunk_interval <= 0:
            raise ValueError("chunk_size and chunk_interval must be positive")
        if split_size < 0 or split_duration < 0:
            raise ValueError("split_size (bytes) and split_duration (s) must be >= 0 (0 = no split)")
        try:
            self._comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                          "none": CompressionType.NONE}[compression]
        except KeyError:
            raise ValueError(f"compression must be zstd, lz4 or none, got {compression!r}") from None
        self.path = Path(path)
        self.chunk_size = chunk_size
        self.chunk_interval = chunk_interval
        self.split_size = int(split_size)
        self.split_duration = float(split_duration)
        self.topics = dict(TOPICS if topics is None else topics)
        self.metadata = {name: {k: str(v) for k, v in values.items()} for name, values in (metadata or {}).items()}
        self.stats = RecorderStats()
        # SimpleQueue: a put is a C call with no condition variable to notify (the event loop queues ~7
        # messages per scan); write() keeps the bound (queue_size, <= 0: none) from its size
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._queue_size = queue_size
        self._latched: dict[str, tuple] = {}
        self._error: BaseException | None = None
        self._closed = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._open(0)
        except OSError as exc:
            raise RecorderError(f"cannot create recording {self._file_path(0)}: {exc.strerror or exc}") from exc
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    @property
    def splitting(self) -> bool:
        return self.split_size > 0 or self.split_duration > 0

    def _file_path(self, index: int) -> Path:
        """The file of split ``index``: the path itself when not splitting, else <stem>_NNNN<suffix>."""
        if not self.splitting:
            return self.path
        return self.path.with_name(f"{self.path.stem}_{index:04d}{self.path.suffix or '.mcap'}")

    def _open(self, index: int) -> None:
        path = self._file_path(index)
        self._index = index
        self._file = open(path, "wb")
        self._writer = Writer(self._file, chunk_size=self.chunk_size, compression=self._comp)
        self._writer.start(profile=PROFILE, library="glassmap")
        for name, values in self.metadata.items():  # written first: survives a crash
            self._writer.add_metadata(name, values)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._opened = time.monotonic()
        self.stats.files.append(str(path))

    # -- producer side (any thread) ---------------------------------------------------------------------
    def write(self, topic: str, msg, log_ns: int, publish_ns: int | None = None) -> bool:
        """Queue one message; returns False (and counts it) if the queue is full or the recorder closed.

        ``msg`` may be a zero-argument callable returning the message: it is then built in the writer thread
        (so the caller does not pay for it); or ``bytes``: the message already serialised as CDR."""
        if self._closed or self._error is not None:
            self.stats.dropped[topic] += 1
            return False
        if 0 < self._queue_size <= self._queue.qsize():
            self.stats.dropped[topic] += 1
            return False
        self._queue.put((topic, msg, int(log_ns), int(publish_ns if publish_ns is not None else log_ns)))
        return True

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
        if self._error is not None:
            try:
                self._file.close()
            except OSError:
                pass  # the buffered tail cannot be written either: the error is reported below
        else:
            try:
                self._writer.finish()
                self._file.close()
            except OSError as exc:
                self._stop_on_error(exc)
        if self._error is not None:
            raise RecorderError(self.stats.stopped) from self._error

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

    def _split_due(self) -> bool:
        if not self.splitting:
            return False
        if self.split_duration > 0 and time.monotonic() - self._opened >= self.split_duration:
            return True
        return self.split_size > 0 and self._file.tell() >= self.split_size

    def _next_split(self) -> None:
        """Finish the current file (complete, readable on its own) and open the next one."""
        self._writer.finish()
        self._file.close()
        self._open(self._index + 1)
        for topic, (msg, log_ns, pub_ns) in self._latched.items():
            self._add(topic, msg, log_ns, pub_ns, count=False)

    def _add(self, topic: str, data: bytes, log_ns: int, pub_ns: int, count: bool = True) -> None:
        cid = self._channel(topic)
        self._writer.add_message(channel_id=cid, log_time=log_ns, publish_time=pub_ns, data=data,
                                 sequence=self.stats.written[topic])
        if count:
            self.stats.written[topic] += 1

    def _run(self) -> None:
        ts = typestore()
        for msgtype in sorted(set(self.topics.values())):
            # generate each topic type's serialiser now (8-40 ms each, holding the GIL), not at its first
            # message, when it would hold up the processing thread in the first second of a run
            try:
                ts.get_msgdef(msgtype)
            except Exception as exc:  # reported again with the first message of that type
                log.debug("recorder: no serialiser for %s yet: %s", msgtype, exc)
        last_flush = time.monotonic()
        dirty = False
        while True:
            timeout = max(0.0, self.chunk_interval - (time.monotonic() - last_flush))
            try:
                item = self._queue.get(timeout=timeout if dirty else None)
            except queue.Empty:
                item = None
            for item in itertools.chain((item,), self._queued()):  # what is queued now, then a pause (WAKE_PERIOD)
                if item is _STOP:
                    return
                added = False
                try:
                    if item is not None:
                        topic, msg, log_ns, pub_ns = item
                        if callable(msg):
                            msg = msg()
                        data = bytes(msg if isinstance(msg, bytes) else ts.serialize_cdr(msg, self.topics[topic]))
                        if self._split_due():
                            self._next_split()
                            last_flush, dirty = time.monotonic(), False
                        if dirty and len(data) > self.chunk_size:
                            # a map: in a chunk of its own (the writer closes a chunk past chunk_size), so
                            # that a reader of the other channels (a raw replay) skips it undecompressed
                            self._writer.flush()
                            self.stats.chunks_flushed += 1
                            last_flush = time.monotonic()
                        self._add(topic, data, log_ns, pub_ns)
                        added = True
                        if topic in LATCHED_TOPICS:
                            self._latched[topic] = (data, log_ns, pub_ns)
                        dirty = True
                    if dirty and time.monotonic() - last_flush >= self.chunk_interval:
                        self._writer.flush()  # closes the chunk and flushes the file
                        self.stats.chunks_flushed += 1
                        last_flush = time.monotonic()
                        dirty = False
                except OSError as exc:
                    if item is not None and not added:  # the message whose write failed
                        self.stats.dropped[item[0]] += 1
                    self._stop_on_error(exc)
                    return
                except Exception as exc:  # a bad message must not kill the recording
                    self.stats.errors += 1
                    log.warning("recorder: message on %s not recorded: %s", item[0] if item else "?", exc)
            time.sleep(WAKE_PERIOD)

    def _stop_on_error(self, exc: OSError) -> None:
        full = exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
        why = "the disk is full or a file-size limit was reached" if full else "the file cannot be written"
        self.stats.stopped = (
            f"recording stopped: {why} ({exc.strerror or exc}) writing {self._file_path(self._index)}; "
            f"{self.stats.total_written} messages recorded, mapping goes on. What was written is readable; "
            f"'glassmap recover' completes the last file")
        self._error = exc
        log.error("%s", self.stats.stopped)
        self._drain()

    def _queued(self) -> Iterator:
        """The queued messages, taken one at a time without waiting (what is not taken stays queued)."""
        while True:
            try:
                yield self._queue.get_nowait()
            except queue.Empty:
                return

    def _drain(self) -> None:
        for item in self._queued():
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

    Types are decoded with the glassmap type store (ROS 2 Humble + foxglove + glassmap_msgs). With ``topics``,
    only their messages are read out of the file (:mod:`runtime.mcap_walk`: chunks without any are not
    decompressed)."""
    ts = typestore()
    if topics is None:
        records = iter_mcap_raw(path)
    else:
        from runtime.mcap_walk import iter_channel_messages

        records = iter_channel_messages(path, lambda topic, _schema: topic in topics)
    for r in records:
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
