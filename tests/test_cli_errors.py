"""A world or route the command line names wrongly stops any command with one line naming the problem and
exit status 2, also when the world is first loaded deep inside the command or in a worker process."""

import pytest

from runtime.cli import main


@pytest.mark.parametrize("argv, message", [
    (["glass", "map", "--world", "nope", "--out", "{tmp}"], "no built-in world named 'nope'"),
    (["pose", "bench", "--world", "office", "--route", "nope"], "world 'office' has no route 'nope'"),
    (["glass", "experiment", "--world", "nope", "--trials", "2", "--workers", "2", "--out", "{tmp}"],
     "no built-in world named 'nope'"),
    (["eval", "--worlds", "office,nope", "--generated", "0", "--parts", "pose", "--out", "{tmp}"],
     "no built-in world named 'nope'"),
])
def test_a_bad_world_or_route_is_one_line_and_status_2(tmp_path, capsys, argv, message):
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "error: " in err and message in err and "Traceback" not in err


@pytest.mark.parametrize("argv, message", [
    (["bench", "--recording", "{tmp}/none.mcap", "--pinned-runs", "1"], "recording {tmp}/none.mcap: no such file"),
    (["sim", "generate", "--seed", "-5", "--out", "{tmp}/w.toml"], "a seed is an integer >= 0, got -5"),
    (["pose", "eval", "--seeds=-2", "--out", "{tmp}"], "seeds are integers >= 0, got -2"),
])
def test_a_missing_recording_or_a_negative_seed_is_one_line_and_status_2(tmp_path, capsys, argv, message):
    try:
        status = main([a.format(tmp=tmp_path) for a in argv])
    except SystemExit as e:  # argparse's own errors
        status = e.code
    err = capsys.readouterr().err
    assert status == 2 and message.format(tmp=tmp_path) in err and "Traceback" not in err
