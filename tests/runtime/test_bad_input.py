"""Bad input on the command line: one clear line on stderr, a non-zero exit, no traceback, nothing lost.

Each case of issue 21 part 2, through the real command-line entry point in this process."""

from __future__ import annotations

import socket

import pytest

from runtime.cli import main
from runtime import messages as M
from runtime.recorder import McapRecorder
from tests.runtime.factories import make_odom, make_scan


def run(capsys, *argv: str) -> tuple[int, str]:
    try:
        rc = main(list(argv))
    except SystemExit as exc:  # argparse-style exits (usage errors)
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    return rc, err


def one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: ")
    return lines[0]


def recording(path, n: int = 40):
    """A small complete recording: odometry and scans, several chunks."""
    with McapRecorder(path, chunk_size=4096) as rec:
        for i in range(n):
            rec.write("/odom", M.odometry_msg(make_odom(1.0 + i), 1 + i), 1 + i)
            rec.write("/scan", M.laser_scan_msg(make_scan(1.0 + i, seq=i), 1 + i), 1 + i)
    return path


# -- recover -------------------------------------------------------------------------------------------
def test_recover_a_missing_file(tmp_path, capsys):
    rc, err = run(capsys, "recover", str(tmp_path / "nope.mcap"), str(tmp_path / "out.mcap"))
    assert rc != 0 and "no such file" in one_line(err)
    assert not (tmp_path / "out.mcap").exists()


def test_recover_into_a_missing_directory(tmp_path, capsys):
    src = recording(tmp_path / "rec.mcap")
    rc, err = run(capsys, "recover", str(src), str(tmp_path / "missing" / "out.mcap"))
    assert rc != 0 and "does not exist" in one_line(err)


@pytest.mark.parametrize("content, says", [(b"", "empty file, not a recording"),
                                           (b"\x0eDi\xa2}" * 20, "not an MCAP recording")])
def test_recover_an_empty_or_garbage_file(tmp_path, capsys, content, says):
    src = tmp_path / "bad.mcap"
    src.write_bytes(content)
    rc, err = run(capsys, "recover", str(src), str(tmp_path / "out.mcap"))
    assert rc != 0 and says in one_line(err)
    assert not (tmp_path / "out.mcap").exists()  # no 45-byte file that no reader opens


def test_recover_a_file_cut_before_its_first_chunk(tmp_path, capsys):
    full = recording(tmp_path / "rec.mcap").read_bytes()
    src = tmp_path / "cut.mcap"
    src.write_bytes(full[:60])  # the magic and part of the header: no message
    rc, err = run(capsys, "recover", str(src), str(tmp_path / "out.mcap"))
    assert rc != 0 and "no complete message" in one_line(err)
    assert not list(tmp_path.glob("out.mcap*"))


def test_recover_a_cut_recording_keeps_its_messages_and_metadata(tmp_path, capsys):
    from runtime.readers import read_metadata
    from runtime.recorder import read_mcap

    path = tmp_path / "rec.mcap"
    with McapRecorder(path, chunk_size=4096, metadata={"glassmap": {"time_offset_ns": "7"}}) as rec:
        for i in range(40):
            rec.write("/scan", M.laser_scan_msg(make_scan(1.0 + i, seq=i), 1 + i), 1 + i)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    n_cut = sum(1 for _ in read_mcap(cut))
    rc, _ = run(capsys, "recover", str(cut), str(tmp_path / "fixed.mcap"))
    assert rc == 0 and n_cut > 0
    assert sum(1 for _ in read_mcap(tmp_path / "fixed.mcap")) == n_cut
    assert read_metadata(tmp_path / "fixed.mcap") == {"time_offset_ns": "7"}


# -- run: URLs and paths, checked before anything starts ----------------------------------------------------
@pytest.mark.parametrize("args, says", [
    (("--laser", "foo"), "laser URL: unsupported device URL 'foo'"),
    (("--laser", "http://x"), "laser URL: unsupported device URL 'http://x'"),
    (("--laser", "tcp://host:notaport"), "laser URL: bad URL 'tcp://host:notaport'"),
    (("--base", "bogus://x"), "base URL: unsupported device URL 'bogus://x'"),
    (("--base", "serial:///dev/ttyUSB0?baud=abc"), "base URL: bad serial URL"),
    (("--laser", "tcp://127.0.0.1:9", "--base", "none", "--record", "/missing/dir/x.mcap"),
     "directory /missing/dir does not exist"),
])
def test_run_refuses_bad_urls_and_paths_before_connecting(tmp_path, capsys, monkeypatch, args, says):
    import runtime.app

    def no_runtime(*a, **kw):
        raise AssertionError("the runtime must not start")

    monkeypatch.setattr(runtime.app, "Runtime", no_runtime)
    rc, err = run(capsys, "run", "--out", str(tmp_path), *args)
    assert rc == 2 and says in one_line(err)
    assert not (tmp_path / "missing").exists()


def test_config_given_a_directory(tmp_path, capsys):
    rc, err = run(capsys, "run", "--config", str(tmp_path))
    assert rc != 0 and "is a directory" in one_line(err)


# -- pioneer emulate: port in use ---------------------------------------------------------------------------
def test_pioneer_emulate_on_a_port_in_use(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        rc, err = run(capsys, "pioneer", "emulate", "--tcp", str(port))
    assert rc != 0 and f"cannot serve on tcp port {port}" in one_line(err)


# -- replay -------------------------------------------------------------------------------------------------
def test_replay_of_a_cut_recording_says_so_and_points_to_recover(tmp_path, capsys):
    full = recording(tmp_path / "rec.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    rc, err = run(capsys, "replay", str(cut), "--no-progress", "--out", str(tmp_path / "out"))
    line = one_line(err)
    assert rc != 0 and "cut short" in line and f"glassmap recover {cut}" in line


@pytest.mark.parametrize("content", [b"", b"\x00garbage" * 10])
def test_replay_of_an_empty_or_garbage_file_says_it_is_not_a_recording(tmp_path, capsys, content):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    rc, err = run(capsys, "replay", str(bad), "--no-progress")
    line = one_line(err)
    assert rc != 0 and ("empty file, not a recording" in line or "not an MCAP recording" in line)


def test_replay_limit_must_be_positive(tmp_path, capsys):
    rc, err = run(capsys, "replay", str(recording(tmp_path / "rec.mcap")), "--limit", "-3")
    assert rc == 2 and "--limit must be >= 1" in one_line(err)


def test_replay_of_a_file_of_another_kind_says_so_before_any_progress_bar(tmp_path, capsys):
    other = tmp_path / "notes.txt"
    other.write_text("not a recording")
    rc, err = run(capsys, "replay", str(other))  # with the progress bar on
    assert rc != 0 and "unknown file kind (expected .mcap, .bag, .db3 or a ROS 2 bag directory)" in one_line(err)


# -- worlds, routes, seeds, recordings named on any command ---------------------------------------------------
@pytest.mark.parametrize("argv, says", [
    (["glass", "map", "--world", "nope", "--out", "{tmp}"], "no built-in world named 'nope'"),
    (["pose", "bench", "--world", "office", "--route", "nope"], "world 'office' has no route 'nope'"),
    # met in a worker process (a WorldFileError that could not be unpickled broke the pool)
    (["glass", "experiment", "--world", "nope", "--trials", "2", "--workers", "2", "--out", "{tmp}"],
     "no built-in world named 'nope'"),
    (["eval", "--worlds", "office,nope", "--generated", "0", "--parts", "pose", "--out", "{tmp}"],
     "no built-in world named 'nope'"),
    (["bench", "--recording", "{tmp}/none.mcap", "--pinned-runs", "1"], "{tmp}/none.mcap: no such file"),
    (["sim", "generate", "--seed", "-5", "--out", "{tmp}/w.toml"], "a seed is an integer >= 0, got -5"),
    (["pose", "eval", "--seeds=-2", "--out", "{tmp}"], "seeds are integers >= 0, got -2"),
])
def test_a_bad_world_route_seed_or_recording_anywhere_is_one_line_and_status_2(tmp_path, capsys, argv, says):
    rc, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert rc == 2 and says.format(tmp=tmp_path) in err.splitlines()[-1]
