"""The map worker: a helper process that turns copies of the maps into files and recorded messages.

Colouring and encoding a PNG, building the /map and /glass/map messages (a few MB of numpy work) and the
first import of matplotlib hold the GIL for tens to hundreds of milliseconds. In a thread of the runtime's
process that time is taken from the scans (the live p99 latency doubled on the development machine); in
this process it is not. The runtime hands over a picklable :class:`~glassmap.mapping.MapCopy` (a ~1 ms copy
of two layers made between two scans) and gets back the paths of the files or the CDR-serialised messages.

The process is started (spawned, not forked: the runtime has threads) before the devices connect, and ends
with the runtime, also after a SIGKILL of the runtime (a watchdog thread in the worker polls its parent).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import multiprocessing
import os
import time
from concurrent.futures.process import BrokenProcessPool

from glassmap.mapping import MapCopy
from runtime.tuning import background_priority

log = logging.getLogger(__name__)


class MapWorker:
    """One helper process for map exports and map messages; use from the event loop.

    If the process cannot start (spawning re-imports the main module, which is impossible for code fed to
    ``python -`` or run in some notebooks), the work is done in a thread of this process instead, with a
    warning: everything still works, scans are only slower while maps are exported."""

    def __init__(self) -> None:
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self.in_process = False

    async def start(self) -> None:
        """Start the process and wait until it has imported what it needs (~1-2 s, once)."""
        if self._pool is not None or self.in_process:
            return
        self._pool = concurrent.futures.ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn"), initializer=_init, initargs=(os.getpid(),))
        try:
            await asyncio.get_running_loop().run_in_executor(self._pool, os.getpid)
        except BrokenProcessPool as exc:
            self.shutdown()
            self.in_process = True
            log.warning("the map worker process did not start (%s); maps are made in a thread of this process "
                        "instead (scans are slower while maps are exported)", exc)

    async def export(self, maps: MapCopy, out_dir: str, stem: str) -> dict[str, str]:
        """Write PNG, .npy + .json, PGM + YAML (see :func:`glassmap.mapping.export_maps`); returns the paths.
        Raises OSError when the files cannot be written, BrokenProcessPool when the worker died."""
        return await self.run(maps.export, out_dir, stem)

    async def map_messages(self, maps: MapCopy, stamp_ns: int, frame_id: str) -> tuple[bytes, bytes]:
        """CDR of the nav_msgs/OccupancyGrid (/map) and the foxglove_msgs/Grid (/glass/map) of ``maps``."""
        return await self.run(map_messages, maps, stamp_ns, frame_id)

    async def graph_messages(self, snapshot, stamp_ns: int, frame_id: str, time_base) -> list[tuple[str, bytes]]:
        """CDR of the pose graph's messages (:func:`runtime.graph_worker.graph_messages`)."""
        from runtime.graph_worker import graph_messages

        return await self.run(graph_messages, snapshot, stamp_ns, frame_id, time_base)

    def shutdown(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    async def run(self, fn, *args):
        """``fn(*args)`` in the worker process (``fn`` and its arguments picklable); raises what it raises,
        BrokenProcessPool when the worker died."""
        await self.start()
        if self._pool is None:
            return await asyncio.to_thread(fn, *args)
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)


# -- run in the worker process ---------------------------------------------------------------------------
def _init(parent_pid: int) -> None:
    """Worker start: end when the runtime's process is gone (a SIGKILL runs no clean-up there), lower
    priority than the scans, then import what the work needs so that the first export is not slow."""
    import importlib
    import threading

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    background_priority()
    for name in ("matplotlib.image", "glassmap.render", "runtime.messages"):
        importlib.import_module(name)


def map_messages(maps: MapCopy, stamp_ns: int, frame_id: str) -> tuple[bytes, bytes]:
    """CDR of the /map (nav_msgs/OccupancyGrid) and /glass/map (foxglove_msgs/Grid) messages of ``maps``
    (in whatever process calls it)."""
    from runtime import messages as M

    g = maps.grid
    origin, res = (float(g.origin[0]), float(g.origin[1])), float(g.resolution)
    ts = M.typestore()
    occ = M.occupancy_grid_msg(maps.occupancy.probability(), origin, res, stamp_ns, frame_id)
    glass = M.glass_grid_msg(maps.confidence_map(), origin, res, stamp_ns, frame_id)
    return (bytes(ts.serialize_cdr(occ, M.TOPICS["/map"])), bytes(ts.serialize_cdr(glass, M.TOPICS["/glass/map"])))


def export_in_child(maps: list[MapCopy], out_dir: str, stems: list[str]) -> list[dict[str, str]]:
    """``maps[k].export(out_dir, stems[k])`` (PNG, .npy + .json, PGM + YAML) in a new spawned process, so that
    the PNG's matplotlib is never loaded into this one (the replay's peak memory); in this process, with a
    warning, when no process can be started. Returns the paths; raises what the exports raise (OSError)."""
    try:
        with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            return pool.submit(_export_all, maps, out_dir, stems).result()
    except (BrokenProcessPool, AssertionError) as exc:  # AssertionError: a daemonic process may have no children
        log.warning("no process for the map export (%s); exporting in this process", exc or type(exc).__name__)
        return _export_all(maps, out_dir, stems)


def _export_all(maps: list[MapCopy], out_dir: str, stems: list[str]) -> list[dict[str, str]]:
    return [m.export(out_dir, s) for m, s in zip(maps, stems, strict=True)]
