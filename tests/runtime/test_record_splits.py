"""Field recording sessions: recordings split by size and by duration, and a full disk (a file-size limit on
the writing process) stopping the recording cleanly while the rest goes on."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from runtime import messages as M
from runtime.output_args import parse_size
from runtime.recorder import LATCHED_TOPICS, McapRecorder, read_mcap, recover_mcap
from runtime.sink import RecordingSink
from tests.runtime.factories import make_odom, make_scan

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(180)


def _session(sink: RecordingSink, n: int, pause: float = 0.0) -> None:
    """A small session through the recording sink: /tf_static once, then scans and odometry."""
    tb = sink.tb
    tf = M.transform_stamped(tb.ns(1.0), "base_link", "laser", 0.1, 0.0, 0.0)
    sink.rec.write("/tf_static", M.tf_msg([tf]), tb.ns(1.0))
    for k in range(n):
        sink.odometry(make_odom(1.0 + 0.025 * k, x=0.001 * k))
        sink.scan(make_scan(1.0 + 0.025 * k, seq=k))
        if pause:
            time.sleep(pause)


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    """(topic, log_ns, sha of data) of every message, with the standard mcap reader (needs a complete file)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None, f"{path} has no summary: not a complete file"
        return [(ch.topic, m.log_time, hashlib.sha1(m.data).hexdigest())
                for _, ch, m in reader.iter_messages(log_time_order=False)]


def _check_splits(files: list[str], unsplit: Path) -> None:
    assert len(files) >= 3
    assert files == sorted(files)  # names sort in recording order
    whole = _messages(unsplit)
    parts, latched_repeats = [], 0
    for i, f in enumerate(files):
        msgs = _messages(Path(f))
        assert msgs[0][0] == "/tf_static"  # each split opens on its own with the static transform
        if i > 0:
            latched_repeats += sum(1 for m in msgs if m[0] in LATCHED_TOPICS)
            msgs = [m for m in msgs if m[0] not in LATCHED_TOPICS]
        parts.extend(msgs)
        with AnyReader([Path(f)]) as r:  # rosbags opens each split as a ROS 2 bag
            assert r.message_count == len(_messages(Path(f)))
    assert latched_repeats == len(files) - 1
    assert Counter(parts) == Counter(whole)  # nothing lost or repeated at the boundaries
    assert [m[1] for m in parts] == [m[1] for m in whole]  # ... and in the same order


def test_split_by_size_holds_every_message_once(tmp_path):
    tb = M.TimeBase(1_700_000_000_000_000_000)
    whole = McapRecorder(tmp_path / "whole.mcap", chunk_size=16 * 1024)
    split = McapRecorder(tmp_path / "field.mcap", chunk_size=16 * 1024, split_size=parse_size("64k"))
    for rec in (whole, split):
        _session(RecordingSink(rec, tb), 300)
        rec.close()
    assert [Path(f).name for f in split.stats.files[:2]] == ["field_0000.mcap", "field_0001.mcap"]
    assert not (tmp_path / "field.mcap").exists()
    for f in split.stats.files[:-1]:
        assert Path(f).stat().st_size < 64 * 1024 + 2 * 16 * 1024  # the size, plus at most a chunk
    assert split.stats.written == whole.stats.written
    _check_splits(split.stats.files, tmp_path / "whole.mcap")


def test_split_by_duration(tmp_path):
    tb = M.TimeBase(1_700_000_000_000_000_000)
    whole = McapRecorder(tmp_path / "whole.mcap")
    split = McapRecorder(tmp_path / "field.mcap", split_duration=0.25)
    sinks = [RecordingSink(whole, tb), RecordingSink(split, tb)]

    class Both:  # the same messages to both, at the same pace
        def write(self, *a):
            for s in sinks:
                s.rec.write(*a)

    _session(RecordingSink(Both(), tb), 60, pause=0.02)
    whole.close()
    split.close()
    _check_splits(split.stats.files, tmp_path / "whole.mcap")


def test_parse_size():
    assert parse_size("500M") == 500 * 1024**2 and parse_size("2G") == 2 * 1024**3
    assert parse_size("1000") == 1000 and parse_size("64k") == 65536
    with pytest.raises(ValueError):
        parse_size("lots")


_FULL_DISK = """
import json, resource, signal, sys, time
sys.path.insert(0, {root!r})
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead
resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
from runtime import messages as M
from runtime.recorder import McapRecorder, RecorderError
from runtime.sink import RecordingSink
from tests.runtime.factories import make_odom, make_scan
rec = McapRecorder({path!r}, chunk_size=8192, chunk_interval=0.05)
submitted = 0
write = rec.write
def counted(*args, **kwargs):
    global submitted
    submitted += 1
    return write(*args, **kwargs)
rec.write = counted
sink = RecordingSink(rec, M.TimeBase(1_700_000_000_000_000_000))
for k in range(600):  # the producer (the runtime) never notices: write() never blocks or raises
    sink.odometry(make_odom(1.0 + 0.025 * k))
    sink.scan(make_scan(1.0 + 0.025 * k, seq=k))
    time.sleep(0.001)
try:
    rec.close()
    err = ""
except RecorderError as exc:
    err = str(exc)
print(json.dumps({{"error": err, "written": rec.stats.total_written, "dropped": rec.stats.total_dropped,
                  "submitted": submitted}}))
"""


def test_full_disk_stops_the_recording_cleanly_and_what_was_written_reads_back(tmp_path):
    path = tmp_path / "field.mcap"
    limit = 200 * 1024
    code = _FULL_DISK.format(root=str(ROOT), limit=limit, path=str(path))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert "the disk is full or a file-size limit was reached" in out["error"]
    assert out["written"] > 0 and out["dropped"] > 0
    assert out["written"] + out["dropped"] == out["submitted"]  # nothing lost without being counted
    # one clear message, no traceback
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len([ln for ln in lines if "recording stopped" in ln]) == 1, p.stderr
    assert "Traceback" not in p.stderr
    assert path.stat().st_size <= limit
    # what was written reads back, and recovers into a complete file
    got = Counter(t for t, _, _, _ in read_mcap(path))
    assert got["/scan"] > 10 and got["/odom"] > 10
    fixed = tmp_path / "fixed.mcap"
    assert recover_mcap(path, fixed).messages == sum(got.values())
    assert len(_messages(fixed)) == sum(got.values())


@pytest.mark.slow
def test_full_disk_during_a_run_mapping_and_robot_safety_go_on(tmp_path):
    """The demo under a file-size limit: the recording stops with one message; scans keep being processed,
    the maps are exported and the robot is stopped and disabled at the end."""
    code = f"""
import resource, signal, sys
sys.path.insert(0, {str(ROOT)!r})
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, ({1536 * 1024}, {1536 * 1024}))
from runtime.cli import main
sys.exit(main(["demo", "--speed", "2", "--duration", "10", "--no-progress", "--out", {str(tmp_path)!r}]))
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=170, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("recording stopped: the disk is full or a file-size limit was reached") == 1, p.stderr
    assert "Traceback" not in p.stderr
    assert "stopped early" in p.stdout
    assert "duration 10 s (emulated) reached" in p.stdout
    processed = int(re.search(r"processed (\d+)", p.stdout).group(1))
    assert processed > 5
    assert (tmp_path / "glass_map.png").is_file()
    got = Counter(t for t, _, _, _ in read_mcap(tmp_path / "demo.mcap"))
    assert got["/scan"] > 0 and got["/pose"] > 0
    assert got["/pose"] < processed  # the scans after the disk filled were mapped, not recorded
