"""``glassmap pose eval`` as a command: runs in parallel give the rows one process gives, in job order; a bad
world or route stops it before the first run, with the routes the world has."""

import csv
from pathlib import Path

import pytest

from runtime.cli import main

WORLD = str(Path(__file__).parent / "data" / "closed-corridor.toml")  # an 8 m drive: a run takes ~1 s


def _rows(out: Path) -> list[dict]:
    with open(out / "pose_eval.csv", newline="") as f:
        return [{k: v for k, v in r.items() if not k.startswith("t_")} for r in csv.DictReader(f)]  # not timings


def test_parallel_runs_give_the_sequential_rows_in_job_order(tmp_path):
    common = ["pose", "eval", "--worlds", WORLD, "--seeds", "0-1", "--route", "default", "--no-progress"]
    assert main(common + ["--workers", "1", "--out", str(tmp_path / "one")]) == 0
    assert main(common + ["--workers", "2", "--out", str(tmp_path / "two")]) == 0
    one, two = _rows(tmp_path / "one"), _rows(tmp_path / "two")
    assert [(r["world"], r["route"], r["seed"]) for r in one] == [("closed-corridor", "main", "0"),
                                                                  ("closed-corridor", "main", "1")]
    assert one == two


@pytest.mark.parametrize("worlds, route, message", [
    (f"{WORLD},room", "short", "world 'room' has no route 'short'; routes: ['loop']"),  # the corridor has one
    (WORLD, "loop", "routes: ['main', 'short']"),
    ("office,no-such-world", None, "no built-in world named 'no-such-world'"),
])
def test_a_bad_world_or_route_stops_before_any_run(tmp_path, capsys, worlds, route, message):
    args = ["pose", "eval", "--worlds", worlds, "--out", str(tmp_path), "--no-progress"]
    assert main(args + (["--route", route] if route else [])) == 2
    out, err = capsys.readouterr()
    assert err.startswith("error: ") and message in err and out == ""  # no run's line: before the first run
    assert not (tmp_path / "pose_eval.csv").exists()
