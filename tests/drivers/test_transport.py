"""Transports, pty endpoints and the capture replayer, through real ptys and loopback sockets."""

import asyncio

import pytest

from drivers.capture import Capture, CaptureRecorder, Chunk
from drivers.errors import InvalidURL, TransportClosed, TransportError
from drivers.transport import TransportURL, open_transport
from tests.fakes.replay import replay_over_pty, replay_over_tcp


def test_url_parsing():
    assert TransportURL.parse("tcp://192.168.0.10:10940") == TransportURL("tcp", host="192.168.0.10", port=10940)
    u = TransportURL.parse("serial:///dev/ttyUSB0?baud=9600")
    assert (u.scheme, u.path, u.baud) == ("serial", "/dev/ttyUSB0", 9600)
    for bad in ("tcp://host", "udp://x:1", "serial://", "serial:///dev/x?baud=fast"):
        with pytest.raises(ValueError):
            TransportURL.parse(bad)


@pytest.mark.parametrize("url, says", [
    ("foo", "unsupported device URL 'foo'"),
    ("http://x", "unsupported device URL 'http://x'"),
    ("tcp://host:notaport", "'tcp://host:notaport'.*notaport"),
    ("tcp://host:99999", "out of range"),
    ("tcp://host", "expected tcp://HOST:PORT"),
    ("bogus://x", "unsupported device URL"),
    ("serial:///dev/ttyUSB0?baud=abc", "baud must be a whole number"),
    ("serial://dev/ttyUSB0", "three slashes"),
    ("serial:///dev/ttyUSB0?speed=9600", "unknown option 'speed'"),
])
def test_bad_urls_are_invalid_url_errors_that_say_what_is_wrong(url, says):
    with pytest.raises(InvalidURL, match=says):
        TransportURL.parse(url)


async def test_open_refused_gives_transport_error():
    server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    server.close()
    await server.wait_closed()
    with pytest.raises(TransportError, match="cannot open"):
        await open_transport(f"tcp://127.0.0.1:{port}")


def _capture() -> Capture:
    return Capture("echo", [Chunk(0.0, "tx", b"PING\n"), Chunk(0.01, "rx", b"PONG\n"),
                            Chunk(0.02, "tx", b"BYE\n"), Chunk(0.03, "rx", b"CIAO\n")])


@pytest.mark.parametrize("link", ["pty", "tcp"])
async def test_replay_and_record_round_trip(link, tmp_path):
    cap = _capture()
    if link == "pty":
        path, replayer, endpoint, task = await replay_over_pty(cap)
        url = f"serial://{path}?baud=115200"
    else:
        url, replayer, server = await replay_over_tcp(cap)
    transport = await open_transport(url)
    recorder = CaptureRecorder("echo")
    transport.taps.append(recorder)
    got = b""
    for cmd, want in ((b"PING\n", b"PONG\n"), (b"BYE\n", b"CIAO\n")):
        await transport.write(cmd)
        while not got.endswith(want):
            got += await asyncio.wait_for(transport.read(), 2)
    await transport.close()
    assert got == b"PONG\nCIAO\n"
    assert replayer.stats.tx_mismatches == 0 and replayer.stats.finished
    rec = recorder.capture
    assert rec.tx_bytes() == cap.tx_bytes() and rec.rx_bytes() == cap.rx_bytes()
    rec.save(tmp_path / "c.jsonl")
    assert Capture.load(tmp_path / "c.jsonl").chunks == rec.chunks
    with pytest.raises(TransportClosed):
        await transport.read()
    if link == "pty":
        task.cancel()
        endpoint.close()
    else:
        server.close()


def test_bad_capture_file_names_the_line(tmp_path):
    p = tmp_path / "bad.jsonl"
    p.write_text('{"format": "glassmap-capture", "version": 1}\n{"t": 0, "dir": "up", "data": ""}\n')
    with pytest.raises(ValueError, match=r"bad.jsonl:2: .*dir"):
        Capture.load(p)
