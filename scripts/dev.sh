#!/usr/bin/env bash
# One entry point for newcomers and CI: sets up .venv (idempotent) and runs a job.
#   scripts/dev.sh demo [ARGS...]   set up, then run the main demo (glassmap demo)
#   scripts/dev.sh test [ARGS...]   set up, then run the default test suite (pytest)
#   scripts/dev.sh slow [ARGS...]   set up (+ the dask extra), then run the slow / heavy tests (pytest -m slow)
#   scripts/dev.sh setup            set up only
#   scripts/dev.sh glassmap ARGS    set up, then run any glassmap subcommand
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
venv="${GLASSMAP_VENV:-$here/.venv}"

pick_python() {
  for py in "${PYTHON:-}" python3.11 python3 python; do
    [ -n "$py" ] || continue
    if command -v "$py" >/dev/null 2>&1 && "$py" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      echo "$py"; return 0
    fi
  done
  echo "error: Python 3.11 is required (set PYTHON=/path/to/python3.11)" >&2
  return 1
}

setup() {
  local stamp="$venv/.glassmap-setup" want
  want="$(cat pyproject.toml scripts/dev.sh tests/runtime/live_client/package-lock.json | sha256sum | cut -c1-16)"
  if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then return 0; fi
  local py; py="$(pick_python)"
  echo "== setting up $venv (one time; torch is large)" >&2
  [ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --upgrade pip
  # torch first and pinned: a range admitting newer releases would pull the CUDA builds.
  "$venv/bin/python" -m pip install --quiet "torch==2.13.0"
  "$venv/bin/python" -m pip install --quiet -e ".[test]"
  # test tool only: Foxglove's WebSocket client under Node checks the live view (skipped without node)
  if command -v npm >/dev/null 2>&1; then
    npm ci --prefix tests/runtime/live_client --no-audit --no-fund --loglevel=error \
      || echo "note: npm ci failed: the live-view tests will be skipped" >&2
  else
    echo "note: npm not found: the live-view tests will be skipped" >&2
  fi
  warm_kernels
  echo "$want" > "$stamp"
}

# Compile the numba kernels once and cache them beside the modules (~40 s): a short demo through both
# emulators and a replay of its raw bytes use every kernel the runtime needs. Without this the first run
# compiles them itself: it waits 12-40 s at start-up and its peak memory is ~390 MiB instead of ~200.
warm_kernels() {
  local tmp; tmp="$(mktemp -d)"
  echo "== compiling the kernels (one time, ~40 s)" >&2
  if "$venv/bin/glassmap" demo --duration 3 --out "$tmp" --no-progress >"$tmp/log" 2>&1 \
      && "$venv/bin/glassmap" replay "$tmp/demo.mcap" --source raw --out "$tmp/replay" --no-progress >>"$tmp/log" 2>&1; then
    rm -rf "$tmp"
  else
    echo "note: the warm-up run failed (log: $tmp/log): the first run will compile the kernels itself" >&2
  fi
}

cmd="${1:-help}"; shift || true
case "$cmd" in
  setup) setup ;;
  demo) setup; exec "$venv/bin/glassmap" demo "$@" ;;
  test) setup; exec "$venv/bin/python" -m pytest "$@" ;;
  slow) setup  # the slow suite also covers the optional Dask extra
        "$venv/bin/python" -m pip install --quiet -e ".[test,dask]"
        exec "$venv/bin/python" -m pytest -m slow "$@" ;;
  glassmap) setup; exec "$venv/bin/glassmap" "$@" ;;
  *) sed -n '2,8p' "$0"; exit 2 ;;
esac
