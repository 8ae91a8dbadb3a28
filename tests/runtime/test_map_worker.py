"""The map worker process: map messages and exports made from a copy of the maps, and its life cycle."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.mapping import GlassMapper
from runtime import messages as M
from runtime.map_worker import MapWorker, map_messages
from runtime.tuning import BACKGROUND_NICE
from tests.helpers import wait_until

ROOT = Path(__file__).resolve().parents[2]


def small_maps():
    """A 4 x 6 cell map: one occupied glass cell, one occupied wall cell, free cells, the rest unknown."""
    occ = OccupancyGrid(MapGrid(0.05, (1.0, -2.0), (4, 6)))
    occ.log_odds[1, 2] = occ.log_odds[2, 4] = 3.0
    occ.log_odds[0, :] = -3.0
    mapper = GlassMapper(occ, classifier=object())  # no classification here: any classifier will do
    mapper.glass.log_odds[1, 2], mapper.glass.log_odds[2, 4] = 4.0, -4.0
    return mapper.copy_maps()


def test_map_messages_are_the_cdr_of_the_recorded_map_messages():
    occ_cdr, glass_cdr = map_messages(small_maps(), 123_000_000_000, "map")
    ts = M.typestore()
    occ = ts.deserialize_cdr(occ_cdr, M.TOPICS["/map"])
    assert (occ.info.width, occ.info.height, occ.info.resolution) == (6, 4, pytest.approx(0.05))
    assert occ.info.origin.position.x == pytest.approx(1.0) and occ.header.frame_id == "map"
    data = np.asarray(occ.data).reshape(4, 6)
    assert data[1, 2] == data[2, 4] == 95 and (data[0] == 5).all() and data[3, 0] == -1
    glass = ts.deserialize_cdr(glass_cdr, M.TOPICS["/glass/map"])
    v = M.grid_values(glass)
    assert v[1, 2] > 0.98 and v[2, 4] < 0.02 and np.isnan(v[0, 0]) and np.isnan(v[3, 5])
    assert M.stamp_to_ns(glass.timestamp) == 123_000_000_000


def test_worker_exports_and_serialises_in_its_own_process(tmp_path):
    async def main():
        worker = MapWorker()
        try:
            await worker.start()
            pid = await worker.run(os.getpid)
            niceness = await worker.run(os.nice, 0)
            paths = await worker.export(small_maps(), str(tmp_path), "w")
            msgs = await worker.map_messages(small_maps(), 5, "map")
        finally:
            worker.shutdown()
        return pid, niceness, paths, msgs

    pid, niceness, paths, msgs = asyncio.run(main())
    assert pid != os.getpid()
    assert niceness == min(os.nice(0) + BACKGROUND_NICE, 19)  # exports wait for the scans on a busy machine
    assert Path(paths["png"]).stat().st_size > 50 and Path(paths["pgm"]).is_file()
    assert msgs == map_messages(small_maps(), 5, "map")


def test_worker_ends_when_the_runtime_process_is_killed():
    script = textwrap.dedent("""
        import asyncio, os, sys, time
        from runtime.map_worker import MapWorker

        async def main():
            w = MapWorker()
            await w.start()
            print(await w.run(os.getpid), flush=True)
            time.sleep(60)

        if __name__ == "__main__":
            asyncio.run(main())
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.PIPE, text=True)
    try:
        worker_pid = int(proc.stdout.readline())
        os.kill(worker_pid, 0)  # alive
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)

    def gone() -> bool:
        try:
            os.kill(worker_pid, 0)
        except ProcessLookupError:
            return True
        return False

    wait_until(gone, what=f"map worker {worker_pid} to end after the runtime process was killed", interval=0.1)


def test_falls_back_to_a_thread_when_the_process_cannot_start(tmp_path):
    """Code fed to ``python -`` cannot be re-imported by a spawned process: the maps are then made in a
    thread, with a warning, and still written."""
    script = textwrap.dedent(f"""
        import asyncio
        from runtime.map_worker import MapWorker
        from tests.runtime.test_map_worker import small_maps

        async def main():
            w = MapWorker()
            await w.start()
            paths = await w.export(small_maps(), {str(tmp_path)!r}, "s")
            w.shutdown()
            print(w.in_process, paths["png"])

        asyncio.run(main())
    """)
    out = subprocess.run([sys.executable, "-"], input=script, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    in_process, png = out.stdout.split()
    assert in_process == "True" and Path(png).is_file()
    assert "map worker process did not start" in out.stderr


def test_final_maps_are_written_in_the_runtime_when_the_worker_died(tmp_path):
    """The runtime makes its final maps in the map worker (the runtime process never imports matplotlib);
    if the worker died, in the runtime itself: the last maps never depend on the worker."""
    from runtime.app import Runtime
    from runtime.config import RuntimeConfig

    async def main():
        rt = Runtime(RuntimeConfig(), processor=object())
        await rt.map_worker.start()
        pid = await rt.map_worker.run(os.getpid)
        os.kill(pid, signal.SIGKILL)
        await asyncio.sleep(0.5)
        try:
            paths = await rt._final(small_maps().export, str(tmp_path), "s")
        finally:
            rt.map_worker.shutdown()
        return paths

    paths = asyncio.run(main())
    assert Path(paths["png"]).is_file() and Path(paths["npy"]).is_file()


def test_export_in_child_writes_what_an_export_here_writes(tmp_path):
    from runtime.map_worker import export_in_child

    maps = small_maps()
    here = maps.export(str(tmp_path / "here"), "a")
    there = export_in_child([maps, maps], str(tmp_path / "child"), ["a", "b"])
    assert [Path(p).name for p in there[1].values()] == [Path(p).name.replace("a", "b", 1) for p in here.values()]
    for key, path in here.items():
        assert Path(there[0][key]).read_bytes() == Path(path).read_bytes()


def test_export_in_child_falls_back_to_this_process(tmp_path, monkeypatch, caplog):
    import concurrent.futures
    from concurrent.futures.process import BrokenProcessPool

    from runtime import map_worker

    class NoProcess(concurrent.futures.ThreadPoolExecutor):
        def __init__(self, *_a, **_k):
            super().__init__(1)

        def submit(self, *_a, **_k):
            raise BrokenProcessPool("no process here")

    monkeypatch.setattr(map_worker.concurrent.futures, "ProcessPoolExecutor", NoProcess)
    out = map_worker.export_in_child([small_maps()], str(tmp_path), ["m"])
    assert Path(out[0]["png"]).is_file() and "exporting in this process" in caplog.text


def test_export_in_child_raises_what_the_export_raises(tmp_path):
    from runtime.map_worker import export_in_child

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(OSError):
        export_in_child([small_maps()], str(blocker / "out"), ["m"])
