"""The raw replay streams the recording: per-device streams from one pass, handshakes from the next write."""

from __future__ import annotations

import pytest

from drivers.capture import Capture
from runtime.raw_replay import PioneerReplay, _Demux, _events, _with_next_tx
from runtime.readers import RawChunk
from tests.pioneer.make_captures import SESSIONS


def _chunks(spec: str) -> list[RawChunk]:
    """'l' laser rx, 'b' base rx, 'T' base tx; chunk k at host time 10 + k."""
    kinds = {"l": ("laser", "rx"), "b": ("base", "rx"), "T": ("base", "tx")}
    return [RawChunk(kinds[c][0], 10.0 + k, kinds[c][1], "tcp://x", bytes([k])) for k, c in enumerate(spec)]


def test_demux_reads_only_as_far_as_a_stream_needs():
    chunks = _chunks("lbTlllb") + [RawChunk("other", 99.0, "rx", "u", b"?")]
    read = []

    def source():
        for c in chunks:
            read.append(c)
            yield c

    demux = _Demux(source(), ("laser", "base"))
    laser, base = demux.stream("laser"), demux.stream("base")
    assert next(laser).data == b"\x00" and len(read) == 1
    assert [c.data for c in base] == [b"\x01", b"\x02", b"\x06"]  # the laser chunks read meanwhile are queued
    assert [c.data for c in laser] == [b"\x03", b"\x04", b"\x05"]  # other devices' chunks are dropped


def test_each_base_write_carries_the_next_write_and_the_order_is_kept():
    evs = list(_with_next_tx(_events(iter(_chunks("bTbbTTb")))))
    assert [(e[1], e[3], e[5]) for e in evs] == [
        (0, "rx", None), (1, "tx", b"\x04"), (2, "rx", None), (3, "rx", None), (4, "tx", b"\x05"),
        (5, "tx", None), (6, "rx", None)]
    assert [e[0] for e in evs] == [10.0 + k for k in range(7)]


@pytest.mark.parametrize("session", SESSIONS, ids=[s.name for s in SESSIONS])
def test_handshakes_from_the_next_write_as_from_all_writes(session):
    cap = Capture.load(session.path)
    txs = [c.data for c in cap.chunks if c.direction == "tx"]
    whole, streamed = PioneerReplay(tx_chunks=txs), PioneerReplay()
    got: dict[int, list] = {id(whole): [], id(streamed): []}
    k = 0
    for c in cap.chunks:
        if c.direction == "tx":
            whole.tx(c.t, c.data)
            streamed.tx(c.t, c.data, txs[k + 1] if k + 1 < len(txs) else None)
            k += 1
        else:
            for rep in (whole, streamed):
                got[id(rep)] += [(o.stamp, o.x, o.y, o.yaw) for o in rep.rx(c.t, c.data)]
    assert got[id(whole)] and got[id(whole)] == got[id(streamed)]
    assert whole.session.links == streamed.session.links
