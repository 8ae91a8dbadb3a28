"""Golden captures: recorded Hokuyo sessions replayed as the sensor over a pty and loopback TCP.

The replayer checks that the client sends exactly the recorded bytes (same handshake, same stream
command, confirmed QT) and the client must get the same scans and counters as when it was recorded.
Re-record the captures with ``python -m tests.fakes.hokuyo_captures``.
"""

import json

import pytest

from drivers.capture import Capture
from drivers.hokuyo.client import HokuyoClient, HokuyoSettings
from drivers.hokuyo.scip import ScanReply, ScipParser
from tests.fakes.hokuyo_captures import CAPTURE_DIR, CAPTURES, stamps_of
from tests.fakes.replay import replay_over_pty, replay_over_tcp

pytestmark = pytest.mark.timeout(60)


async def replay_session(name: str, link: str, realtime: bool = False):
    cap = Capture.load(CAPTURE_DIR / f"{name}.jsonl")
    meta = json.loads(cap.note)
    if link == "pty":
        path, replayer, endpoint, task = await replay_over_pty(cap, realtime=realtime)
        url = f"serial://{path}"
    else:
        url, replayer, server = await replay_over_tcp(cap, realtime=realtime)
    client = await HokuyoClient.connect(url, HokuyoSettings(reconnect=False, **meta["settings"]))
    scans = []
    async for scan in client.scans():
        scans.append(scan)
        if len(scans) >= meta["scans"]:
            break
    await client.close()
    if link == "pty":
        task.cancel()
        endpoint.close()
    else:
        server.close()
    return cap, meta, replayer, client, scans


@pytest.mark.parametrize("link", ["pty", "tcp"])
@pytest.mark.parametrize("name", list(CAPTURES))
async def test_capture_replays_to_the_same_scans_and_counters(name, link):
    cap, meta, replayer, client, scans = await replay_session(name, link)
    assert replayer.stats.tx_mismatches == 0 and replayer.stats.finished
    assert stamps_of(scans) == meta["stamps"]
    want, got = meta["stats"], vars(client.stats)
    for key in ("corrupted", "error_statuses", "garbage_bytes", "unexpected", "reconnects", "dropped"):
        assert got[key] == want[key], key
    assert got["received"] + got["stale"] == want["received"] + want["stale"]


async def test_replay_with_the_original_timing():
    cap, meta, replayer, client, scans = await replay_session("hokuyo-me-stream", "pty", realtime=True)
    assert stamps_of(scans) == meta["stamps"] and replayer.stats.tx_mismatches == 0
    assert vars(client.stats)["corrupted"] == 0 and all(s.intensities is not None for s in scans)


def test_captures_are_golden_files_the_codec_agrees_with():
    """The committed bytes themselves: every scan message decodes, faults are where the note says."""
    for name in CAPTURES:
        cap = Capture.load(CAPTURE_DIR / f"{name}.jsonl")
        meta = json.loads(cap.note)
        items = ScipParser().feed(cap.rx_bytes())
        stamps = [x.timestamp_ms for x in items if isinstance(x, ScanReply) and x.status == "99"]
        assert stamps[: meta["scans"]] == meta["stamps"], name
        tx = cap.tx_bytes()
        assert tx.startswith(b"QT\nPP\nVV\nII\nTM0\n" + b"TM1\n" * 8 + b"TM2\n") and tx.endswith(b"QT\n"), name
