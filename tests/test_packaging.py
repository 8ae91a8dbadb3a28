"""What a pip user gets: declared dependencies, the licence the metadata promises, one Python version."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _declared() -> set[str]:
    return {re.split(r"[<>=!~ \[;]", d, maxsplit=1)[0].lower() for d in PYPROJECT["project"]["dependencies"]}


def test_every_third_party_import_of_the_packages_is_declared():
    imported = set()
    for pkg in ("glassmap", "drivers", "runtime"):
        for f in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    imported |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    imported.add(node.module.split(".")[0])
    # import name -> distribution name, where they differ
    dist = {"skimage": "scikit-image", "serial": "pyserial", "serial_asyncio_fast": "pyserial-asyncio-fast",
            "foxglove": "foxglove-sdk", "yaml": "pyyaml"}
    # imported only where asked for (a clear message), or used when present (threadpoolctl)
    optional = {"hokuyolx", "distributed", "dask", "threadpoolctl"}
    third = {m for m in imported if m not in sys.stdlib_module_names and m not in ("glassmap", "drivers", "runtime")}
    missing = {m for m in third - optional if dist.get(m, m).lower() not in _declared()}
    assert not missing, f"imported but not declared in pyproject.toml: {sorted(missing)}"


def test_license_file_matches_the_metadata():
    assert PYPROJECT["project"]["license"] == "MIT"
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_python_version_agrees_with_dev_sh_and_ci():
    requires = PYPROJECT["project"]["requires-python"]
    assert requires == ">=3.11,<3.12"
    assert "sys.version_info[:2] != (3, 11)" in (ROOT / "scripts" / "dev.sh").read_text()
    assert "scripts/dev.sh test" in (ROOT / ".ci" / "run").read_text()  # CI runs dev.sh, hence 3.11 too
