"""The import graph follows the layers: codecs import nothing of the project but their own package, the core
(``glassmap``) never reaches up into the drivers or the runtime, and the drivers never into the runtime.

Every ``import`` and ``from ... import`` statement is read from the source (also those inside functions),
so a lazy import cannot hide an upward dependency."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> set[str]:
    """Top-level project packages (and modules) a file imports, as dotted names."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def _files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("package, forbidden", [
    ("glassmap", ("drivers", "runtime")),
    ("drivers", ("runtime",)),
])
def test_no_package_imports_a_layer_above_it(package, forbidden):
    bad = [f"{f.relative_to(ROOT)} imports {name}" for f in _files(package) for name in sorted(_imports(f))
           if name.split(".")[0] in forbidden]
    assert not bad, "upward imports:\n" + "\n".join(bad)


@pytest.mark.parametrize("codec", ["drivers/hokuyo/scip.py", "drivers/pioneer/packets.py", "drivers/pioneer/sip.py"])
def test_codecs_are_sans_io(codec):
    """A codec imports no transport, socket, serial port, event loop or other project layer."""
    names = _imports(ROOT / codec)
    io = {"asyncio", "socket", "serial", "serial_asyncio_fast", "selectors", "drivers.transport"}
    assert not names & io, f"{codec} imports {sorted(names & io)}"
    assert not [n for n in names if n.split(".")[0] in ("glassmap", "runtime")]


def test_the_root_command_lives_in_the_top_layer():
    assert not (ROOT / "glassmap" / "cli.py").exists()
    assert 'glassmap = "runtime.cli:main"' in (ROOT / "pyproject.toml").read_text()


@pytest.mark.parametrize("session", ["drivers/hokuyo/session.py", "drivers/pioneer/session.py"])
def test_receive_sessions_are_sans_io(session):
    """The receive sessions shared by the live clients and the raw replay read no clock and touch no link."""
    names = _imports(ROOT / session)
    io = {"asyncio", "socket", "serial", "serial_asyncio_fast", "selectors", "time", "drivers.transport"}
    assert not names & io, f"{session} imports {sorted(names & io)}"
