"""Settings: TOML file, every setting a --section.key flag, ROS-style names, clear errors."""

from __future__ import annotations

import argparse

import pytest

from runtime.config import ConfigError, RuntimeConfig, add_config_flags, config_from_args, load_config
from runtime.teleop import key_to_command


def parse(argv):
    p = argparse.ArgumentParser()
    add_config_flags(p)
    return config_from_args(p.parse_args(argv))


def test_defaults_are_the_hardware_defaults():
    cfg = RuntimeConfig()
    assert cfg.resolved_laser_url() == "tcp://192.168.0.10:10940"
    assert cfg.resolved_base_url() == "serial:///dev/ttyUSB0?baud=9600"
    assert cfg.base.enable_motors is False  # the runtime never moves the robot unless asked
    assert cfg.mapping.deskew is True  # a real laser sweeps while the robot moves


def test_deskew_reaches_the_estimator():
    from runtime.processor import MappingProcessor

    assert MappingProcessor(parse([]).mapping).estimator.config.deskew is True
    assert MappingProcessor(parse(["--mapping.deskew", "false"]).mapping).estimator.config.deskew is False


def test_toml_then_flags(tmp_path):
    f = tmp_path / "robot.toml"
    f.write_text('[laser]\nip_address = "10.0.0.7"\nlaser_frame_id = "hokuyo"\n'
                 '[base]\nport = "/dev/ttyS1"\nbaud = 115200\n[mapping]\nregistration = "direct"\n'
                 '[pipeline]\nmax_scan_age = 1\n')
    cfg = parse(["--config", str(f), "--laser.ip_port", "10941", "--mapping.window", "5",
                 "--base.enable_motors", "true"])
    assert cfg.resolved_laser_url() == "tcp://10.0.0.7:10941"
    assert cfg.laser.laser_frame_id == "hokuyo"
    assert cfg.resolved_base_url() == "serial:///dev/ttyS1?baud=115200"
    assert cfg.mapping.registration == "direct" and cfg.mapping.window == 5
    assert cfg.pipeline.max_scan_age == 1.0 and isinstance(cfg.pipeline.max_scan_age, float)
    assert cfg.base.enable_motors is True


def test_serial_laser_and_tcp_base():
    cfg = parse(["--laser.serial_port", "/dev/ttyACM0", "--base.port", "localhost:8101"])
    assert cfg.resolved_laser_url() == "serial:///dev/ttyACM0?baud=115200"
    assert cfg.resolved_base_url() == "tcp://localhost:8101"


@pytest.mark.parametrize("text, match", [
    ("[lazer]\nip_port = 1\n", r"unknown section \[lazer\]"),
    ("[laser]\nip_prot = 1\n", "unknown key laser.ip_prot"),
    ("[laser]\nip_port = \"ten\"\n", "laser.ip_port: expected int"),
    ("[mapping]\nwindow = 4\n", "mapping.window must be 3 or 5"),
    ("[mapping]\nregistration_sigma = \"world\"\n", "mapping.registration_sigma must be map or anchor"),
    ("[mapping]\nglass_scans = \"every\"\n", "mapping.glass_scans must be keys or all"),
    ("[mapping]\nsurface_margin = -0.1\n", "mapping.hit_margin and surface_margin must be >= 0 m"),
    ("[base]\nmax_sigma = -1\n", r"base.lost_hold \(s\) and base.max_sigma \(m\) must be >= 0"),
    ("[pipeline]\nnice = -30\n", r"pipeline.nice must be in -20 .. 19, got -30"),
    ("[pipeline]\nmemory_reserve = -1\n", r"pipeline.memory_reserve must be >= 0 MiB, got -1"),
    ("[laser\n", r"robot.toml: .*line 1"),
])
def test_bad_files_name_file_key_and_problem(tmp_path, text, match):
    f = tmp_path / "robot.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=match) as err:
        load_config(f)
    assert "robot.toml" in str(err.value)


def test_bad_flag_value():
    with pytest.raises(ConfigError, match="--pipeline.queue_size: expected int"):
        parse(["--pipeline.queue_size", "many"])
    with pytest.raises(ConfigError, match="base.port"):
        parse(["--base.port", "robot"]).resolved_base_url()


def test_teleop_keys():
    v, w, q = key_to_command("w", 0.0, 0.0, 0.5, 1.0)
    assert (v, w, q) == (0.1, 0.0, False)
    v, w, _ = key_to_command("a", 0.5, 0.0, 0.5, 1.0)
    assert v == 0.5 and w == pytest.approx(0.2618, abs=1e-4)
    assert key_to_command("w", 0.5, 0.0, 0.5, 1.0)[0] == 0.5  # clamped to max_v
    assert key_to_command(" ", 0.3, 0.2, 0.5, 1.0) == (0.0, 0.0, False)
    assert key_to_command("q", 0.3, 0.2, 0.5, 1.0) == (0.0, 0.0, True)
