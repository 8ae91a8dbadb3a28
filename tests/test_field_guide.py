"""docs/field-guide.md cannot drift from the code: its commands are parsed here (fast) and run against the
emulated laser and base (slow), with the hardware addresses replaced by the emulators'; the output shown
after a command must have the same lines (labels) as the real output."""

from __future__ import annotations

import asyncio
import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "field-guide.md"
LASER_URL = "tcp://192.168.0.10:10940"
BASE_URL = "serial:///dev/ttyUSB0"


def blocks() -> list[tuple[str, str]]:
    """(language, body) of every fenced block, in order."""
    return re.findall(r"^```(\w*)\n(.*?)^```", GUIDE.read_text(encoding="utf-8"), flags=re.S | re.M)


def commands(body: str) -> list[str]:
    """The commands of a block: backslash continuations joined, blank lines dropped."""
    text = body.replace("\\\n", " ")
    return [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.strip().startswith("#")]


def label(line: str) -> str:
    """What a line of output is about: its first run of words (``VEND``, ``last scan``, ``counters``)."""
    m = re.search(r"[A-Za-z][A-Za-z ]*[A-Za-z]", line)
    return m.group(0).strip() if m else ""


def steps() -> list[tuple[str, str, str | None]]:
    """(kind, text, expected output) with kind 'bash' (a command), 'toml' (settings file)."""
    out: list[tuple[str, str, str | None]] = []
    bs = blocks()
    for i, (lang, body) in enumerate(bs):
        nxt = bs[i + 1] if i + 1 < len(bs) else None
        expected = nxt[1] if nxt is not None and nxt[0] == "text" else None
        if lang == "bash":
            cmds = commands(body)
            for j, c in enumerate(cmds):
                out.append(("bash", c, expected if j == len(cmds) - 1 else None))
        elif lang == "toml":
            out.append(("toml", body, None))
    return out


def glassmap_argv(cmd: str) -> list[str] | None:
    words = shlex.split(cmd)
    while words and re.match(r"^[A-Z_]+=", words[0]):  # VAR=value prefixes
        words.pop(0)
    return words[1:] if words and words[0] == "glassmap" else None


def test_guide_commands_parse_and_settings_load(tmp_path):
    from runtime.cli import build_parser
    from runtime.config import load_config

    kinds = [k for k, _, _ in steps()]
    assert kinds.count("bash") >= 10 and kinds.count("toml") == 1
    parser = build_parser()
    seen = set()
    for kind, text, _ in steps():
        if kind == "toml":
            (tmp_path / "field.toml").write_text(text)
            cfg = load_config(tmp_path / "field.toml")
            assert cfg.resolved_laser_url() == LASER_URL and cfg.resolved_base_url() == BASE_URL + "?baud=9600"
            continue
        argv = glassmap_argv(text)
        if argv is not None:
            parser.parse_args(argv)  # exits (fails the test) on an unknown command or option
            seen.add(" ".join(argv[:2]))
    assert {"hokuyo probe", "hokuyo stream", "pioneer probe", "pioneer drive"} <= seen
    # commands the test does not run change the laptop itself: nothing of glassmap hides there
    for lang, body in blocks():
        if lang == "sh":
            assert not any(glassmap_argv(c) for c in commands(body) if not c.startswith("scripts/dev.sh"))


def _substitute(text: str, laser_url: str, base_url: str) -> str:
    host, port = laser_url.removeprefix("tcp://").rsplit(":", 1)
    pty = base_url.removeprefix("serial://").split("?")[0]
    text = text.replace(BASE_URL + "?baud=9600", base_url).replace(BASE_URL, base_url)
    text = text.replace(LASER_URL, laser_url).replace("192.168.0.10", host).replace("10940", port)
    return text.replace("/dev/ttyUSB0", pty)


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_every_guide_command_runs_against_the_emulators(tmp_path):
    from runtime.devices import DeviceProcess

    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               PYTHONPATH=str(ROOT))
    loop = asyncio.new_event_loop()  # the device process's pipes belong to this loop
    devices = loop.run_until_complete(DeviceProcess.start("office", 1.0, 0))
    try:
        for kind, text, expected in steps():
            text = _substitute(text, devices.laser_url, devices.base_url)
            if kind == "toml":
                (tmp_path / "field.toml").write_text(text)
                continue
            cwd = ROOT if "python -m pytest" in text else tmp_path
            until_ctrl_c = text.startswith("glassmap run") and "--duration" not in text
            p = subprocess.Popen(["bash", "-c", text], cwd=cwd, env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True, start_new_session=True)
            try:
                out, _ = p.communicate(timeout=12 if until_ctrl_c else 240)
            except subprocess.TimeoutExpired:
                if not until_ctrl_c:
                    raise
                os.killpg(p.pid, signal.SIGINT)  # Ctrl-C, as the operator ends a recording
                out, _ = p.communicate(timeout=60)
            assert p.returncode == 0, f"$ {text}\n{out}"
            if "-m hardware" in text:  # the hardware checks ran (against the emulators), not skipped
                assert int(re.search(r"(\d+) passed", out).group(1)) >= 2, out
            if expected:
                for line in expected.splitlines():
                    if label(line):
                        assert label(line) in out, f"$ {text}: no '{label(line)}' in\n{out}"
    finally:
        loop.run_until_complete(devices.stop())
        loop.close()
    assert (tmp_path / "data" / "office_0000.mcap").is_file()  # the split recording's first file
