"""The ``glassmap sim`` command."""

import pytest

from runtime.cli import main
from glassmap.sim.dataset import SimRun


def test_help_lists_sim_commands(capsys):
    with pytest.raises(SystemExit) as e:
        main(["sim", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("run", "render", "bench", "worlds"):
        assert cmd in out


def test_run_writes_a_dataset(tmp_path, capsys):
    out = tmp_path / "room.npz"
    assert main(["sim", "run", "--world", "room", "--seed", "3", "--out", str(out), "--no-progress"]) == 0
    run = SimRun.load(out)
    assert run.world_name == "room" and run.seed == 3 and run.n_scans > 1000
    assert not run.is_glass.any()
    assert "wrote" in capsys.readouterr().out


def test_render_world_blueprint_scan(tmp_path):
    for what in ("world", "blueprint", "scan"):
        p = tmp_path / f"{what}.png"
        args = ["sim", "render", what, "--world", "glass-corridor", "--out", str(p)]
        if what == "scan":
            args += ["--pose", "5,1.25,0"]
        assert main(args) == 0
        assert p.read_bytes()[:4] == b"\x89PNG"


def test_bad_world_file_gives_clear_error(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[[segments]]\na = [0, 0]\nb = [1, 1]\nmaterial = "glas"\n')
    with pytest.raises(SystemExit) as e:
        main(["sim", "render", "world", "--world", str(bad), "--out", str(tmp_path / "x.png")])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "segments[0].material" in err and "unknown material 'glas'" in err


def test_bad_pose(tmp_path):
    with pytest.raises(SystemExit, match="x,y,yaw_deg"):
        main(["sim", "render", "scan", "--pose", "1,2", "--out", str(tmp_path / "s.png")])
