"""The messages of chosen channels of an MCAP file, read without building a record object for the others.

:func:`iter_channel_messages` walks the file's records by hand (opcode u8, length u64 little-endian),
decompresses each chunk (zstd, lz4 or none) and walks the records inside it with ``struct.unpack_from``;
only Schema and Channel records are parsed, and a Message record becomes a
:class:`runtime.recorder.McapRecord` only when its channel is wanted. The output is that of
:func:`runtime.recorder.iter_mcap_raw` (the ``mcap`` library's StreamReader) filtered to the wanted channels,
and so is the behaviour on a file cut short or damaged: reading stops quietly (one line logged at info) at
the first incomplete or damaged record, and a file without summary or footer reads like a complete one. A
chunk is decompressed and walked whole before any of its messages comes out, so a damaged chunk gives none.
CRCs are not checked (StreamReader does not check them by default either): a damaged chunk shows as a
decompression error or as records that run past its end.

A complete file (footer, summary with Schema, Channel and Chunk Index records) also says which channels
each chunk holds messages of: a chunk with none of the wanted channels is skipped without being
decompressed (the recorder writes each map in a chunk of its own, so a raw replay does not decompress the
maps); damage inside a skipped chunk is then not seen.
"""

from __future__ import annotations

import functools
import logging
import os
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

from runtime.recorder import McapRecord

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _CHUNK_INDEX = 0x02, 0x03, 0x04, 0x05, 0x06, 0x08
_TAIL = 9 + 20 + len(MAGIC)  # the footer record (summary start, summary offset start, CRC) and the closing magic

_RECORD = struct.Struct("<BQ")  # opcode, content length
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_SCHEMA_ID_NAME_LEN = struct.Struct("<HI")  # schema id, name length
_CHANNEL_IDS_TOPIC_LEN = struct.Struct("<HHI")  # channel id, schema id, topic length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time (ns), publish time (ns)
_CHUNK_HEAD = struct.Struct("<QQQI")  # message start, end (ns), uncompressed size, uncompressed CRC

Wanted = Callable[[str, str], bool]  # (topic, schema name) -> read this channel's messages?


class DamagedRecord(Exception):
    """A record that is cut short, runs past its container or cannot be decompressed."""


def _string(buf: bytes, pos: int, end: int) -> tuple[str, int]:
    """The length-prefixed UTF-8 string at ``pos`` and the position after it."""
    if pos + 4 > end:
        raise DamagedRecord("string length past the record's end")
    n = _U32.unpack_from(buf, pos)[0]
    pos += 4
    if pos + n > end:
        raise DamagedRecord("string past the record's end")
    try:
        return str(buf[pos:pos + n], "utf-8"), pos + n
    except UnicodeDecodeError as exc:
        raise DamagedRecord(f"string not UTF-8 ({exc.reason})") from None


def _decompress(compression: str, data: bytes, size: int, zstd: list) -> bytes:
    """The records of a chunk; ``zstd``: [the zstandard decompressor], reused across chunks (empty at first)."""
    try:
        if compression == "zstd":
            if not zstd:
                import zstandard

                zstd.append(zstandard.ZstdDecompressor())
            return zstd[0].decompress(data, max_output_size=size)
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.decompress(data)
    except ImportError as exc:
        raise DamagedRecord(f"no decompressor for {compression} chunks ({exc.name} not installed)") from None
    except Exception as exc:  # zstandard.ZstdError, lz4's RuntimeError: the compressed bytes are damaged
        raise DamagedRecord(f"{compression} chunk does not decompress ({exc})") from None
    raise DamagedRecord(f"unsupported chunk compression {compression!r}")


class _Walker:
    """Schemas and channels seen so far, and which channels are wanted (decided at a channel's first message,
    with the schema known then; decided again after any Schema or Channel record)."""

    def __init__(self, wanted: Wanted) -> None:
        self._wanted = wanted
        self._schemas: dict[int, str] = {}  # schema id -> name
        self._channels: dict[int, tuple[str, int]] = {}  # channel id -> (topic, schema id)
        self._chosen: dict[int, tuple[str, str] | None] = {}  # channel id -> (topic, schema name) or None
        self._zstd: list = []

    def _choose(self, channel_id: int) -> tuple[str, str] | None:
        ch = self._channels.get(channel_id)
        if ch is None:  # a message before its channel: StreamReader's readers skip it too
            choice = None
        else:
            topic, schema_id = ch
            msgtype = self._schemas.get(schema_id, "")
            choice = (topic, msgtype) if self._wanted(topic, msgtype) else None
        self._chosen[channel_id] = choice
        return choice

    def records(self, buf: bytes, pos: int, end: int, out: list[McapRecord]) -> None:
        """Walk the records in ``buf[pos:end]``; append the wanted messages to ``out``."""
        chosen = self._chosen
        unpack_record, unpack_u16 = _RECORD.unpack_from, _U16.unpack_from
        while pos < end:
            if pos + 9 > end:
                raise DamagedRecord("record header past the chunk's end")
            op, length = unpack_record(buf, pos)
            start = pos + 9
            pos = start + length
            if pos > end:
                raise DamagedRecord(f"record (opcode {op:#04x}) past the chunk's end")
            if op == _MESSAGE:
                if length < _MESSAGE_HEAD.size:
                    raise DamagedRecord("message record shorter than its fixed fields")
                cid = unpack_u16(buf, start)[0]
                choice = chosen[cid] if cid in chosen else self._choose(cid)
                if choice is not None:
                    log_ns = _U64.unpack_from(buf, start + 6)[0]
                    out.append(McapRecord(choice[0], choice[1], log_ns, buf[start + _MESSAGE_HEAD.size:pos]))
            elif op == _SCHEMA or op == _CHANNEL:
                self.definition(op, buf, start, pos)

    def definition(self, op: int, buf: bytes, pos: int, end: int) -> None:
        """A Schema or Channel record (only the fields the choice needs are read)."""
        if op == _SCHEMA:
            if pos + _SCHEMA_ID_NAME_LEN.size > end:
                raise DamagedRecord("schema record too short")
            sid = _U16.unpack_from(buf, pos)[0]
            name, _ = _string(buf, pos + 2, end)
            self._schemas[sid] = name
        else:
            if pos + _CHANNEL_IDS_TOPIC_LEN.size > end:
                raise DamagedRecord("channel record too short")
            cid, sid = struct.unpack_from("<HH", buf, pos)
            topic, _ = _string(buf, pos + 4, end)
            self._channels[cid] = (topic, sid)
        self._chosen.clear()

    def adopt(self, other: _Walker) -> None:
        """Take the schemas and channels ``other`` has seen (a file's summary)."""
        self._schemas.update(other._schemas)
        self._channels.update(other._channels)
        self._chosen.clear()

    def chunk(self, body: bytes) -> list[McapRecord]:
        """The wanted messages of a Chunk record's content (decompressed and walked whole)."""
        end = len(body)
        if _CHUNK_HEAD.size > end:
            raise DamagedRecord("chunk record too short")
        size = _CHUNK_HEAD.unpack_from(body, 0)[2]
        compression, pos = _string(body, _CHUNK_HEAD.size, end)
        if pos + 8 > end:
            raise DamagedRecord("chunk record too short")
        n = _U64.unpack_from(body, pos)[0]
        pos += 8
        if pos + n > end:
            raise DamagedRecord("chunk records past the chunk's end")
        out: list[McapRecord] = []
        if compression:
            data = _decompress(compression, body[pos:pos + n], size, self._zstd)
            self.records(data, 0, len(data), out)
        else:
            self.records(body, pos, pos + n, out)
        return out


def _unwanted_chunks(f, size: int, walker: _Walker) -> set[int]:
    """File offsets of the Chunk records that hold messages of none of the channels ``walker`` wants, from the
    summary, whose Schema and Channel records define every channel up front: ``walker`` learns them, so that
    a channel defined in a skipped chunk (one that closed before the channel's first message) is known when
    its messages come. Empty for a file without a footer or summary, or with a summary that does not parse."""
    if size < len(MAGIC) + _TAIL:
        return set()
    f.seek(size - _TAIL)
    tail = f.read(_TAIL)
    if tail[9 + 20:] != MAGIC or tail[0] != _FOOTER:
        return set()
    start = _U64.unpack_from(tail, 9)[0]
    if not len(MAGIC) <= start < size - _TAIL:
        return set()
    f.seek(start)
    buf = f.read(size - _TAIL - start)
    summary = _Walker(walker._wanted)  # adopted by ``walker`` only once the whole summary parses
    chunks: list[tuple[int, list[int]]] = []  # (chunk offset, its channels)
    pos = 0
    try:
        while pos < len(buf):
            op, length = _RECORD.unpack_from(buf, pos)
            body, pos = pos + _RECORD.size, pos + _RECORD.size + length
            if pos > len(buf):
                return set()
            if op == _SCHEMA or op == _CHANNEL:
                summary.definition(op, buf, body, pos)
            elif op == _CHUNK_INDEX:  # start and end time, chunk offset and length, then {channel: offset}
                offset = _U64.unpack_from(buf, body + 16)[0]
                n = _U32.unpack_from(buf, body + 32)[0]
                if n % 10 or body + 36 + n > pos:
                    return set()
                chunks.append((offset, [_U16.unpack_from(buf, body + 36 + i)[0] for i in range(0, n, 10)]))
    except (DamagedRecord, struct.error):
        return set()
    walker.adopt(summary)
    return {off for off, ids in chunks if ids and all(walker._choose(cid) is None for cid in ids)}


def iter_channel_messages(path: str | Path, wanted: Wanted) -> Iterator[McapRecord]:
    """The messages of the channels ``wanted(topic, schema name)`` accepts, in file order (see the module
    docstring: also from a file cut short or damaged; stops at the footer)."""
    wanted = functools.cache(wanted)  # asked once per channel, by the summary and the walk alike
    walker = _Walker(wanted)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if f.read(len(MAGIC)) != MAGIC:
            log.info("%s: not an MCAP file (no magic at its start)", path)
            return
        skip = _unwanted_chunks(f, size, walker)
        f.seek(len(MAGIC))
        pos = len(MAGIC)
        while True:
            head = f.read(_RECORD.size)
            if len(head) < _RECORD.size:
                log.info("%s: stopped reading at an incomplete record (the file ends without a footer)", path)
                return
            op, length = _RECORD.unpack(head)
            pos += _RECORD.size
            if length > size - pos:  # also a damaged length: never allocated
                log.info("%s: stopped reading at an incomplete record (opcode %#04x)", path, op)
                return
            if op == _FOOTER:
                return
            if op not in (_CHUNK, _MESSAGE, _SCHEMA, _CHANNEL) or (op == _CHUNK and pos - _RECORD.size in skip):
                f.seek(length, os.SEEK_CUR)
                pos += length
                continue
            body = f.read(length)
            pos += len(body)
            if len(body) < length:
                log.info("%s: stopped reading at an incomplete record (opcode %#04x)", path, op)
                return
            try:
                if op == _CHUNK:
                    out = walker.chunk(body)
                else:
                    out = []
                    walker.records(head + body, 0, _RECORD.size + length, out)
            except (DamagedRecord, struct.error) as exc:
                log.info("%s: stopped reading at a damaged record (%s)", path, exc)
                return
            yield from out
