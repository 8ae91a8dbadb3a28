"""The pose-graph worker: same graph as the back end run in line (so a replay reproduces it), whether or not
corrected maps were published during the run and in a process or a thread, a corrected grid at the end, a
crashed or failing worker reported instead of waited for, a clean stop, the processor's hook, and the
recorded trajectory + corrected map."""

import os
import signal
import time
from dataclasses import replace

import numpy as np
import pytest

from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from runtime import messages as M
from runtime.config import MappingConfig
from runtime.graph_worker import GraphWorker, GraphWorkerError, graph_messages
from runtime.processor import MappingProcessor
from runtime.recorder import McapRecorder, read_mcap
from runtime.sink import RecordingSink
from tests.pose.test_loop_closure import _keys, _ring, _route
from tests.runtime.factories import make_odom, make_scan


def _short_keys():
    truth = _route([(-8.5, -4.5), (0.0, -4.5)])
    return _keys(_ring(), truth, yaw_bias=0.001)


def _final_snapshot(keys, **kwargs):
    """The graph of ``keys`` built by a worker, read when it has finished (the worker then closed)."""
    w = GraphWorker(BackEndConfig(), **kwargs)
    try:
        for k in keys:
            w.submit(k)
        return w.finish()
    finally:
        w.close()


def test_worker_builds_the_same_graph_as_the_back_end_in_line_and_a_corrected_grid():
    keys = _short_keys()
    inline = GraphBackEnd(BackEndConfig())
    for k in keys:
        inline.add(k)
    w = GraphWorker(BackEndConfig())
    try:
        for k in keys:
            w.submit(k)
        snap = w.finish(timeout=60.0)
    finally:
        w.close()
    np.testing.assert_array_equal(snap.poses, inline.poses())
    np.testing.assert_array_equal(snap.stamps, [k.stamp for k in keys])
    assert snap.grid is not None and snap.version == 1
    assert snap.grid.occupied().sum() > 100  # the ring's walls
    corr, lag = w.latest_correction()
    ref = inline.latest()
    np.testing.assert_allclose(corr.correction, ref.correction, atol=1e-9)
    # the worker's was read before the final solve (the newest nodes chained), this one after: first order
    np.testing.assert_allclose(corr.cov, ref.cov, rtol=1e-2, atol=1e-12)
    assert corr.closures == len(inline.closures) and lag == 0  # finished: every key scan is in the graph


def test_sink_records_the_optimised_path_and_the_corrected_map(tmp_path):
    keys = _short_keys()[:12]
    snap = _final_snapshot(keys)
    tb = M.TimeBase(offset_ns=1_700_000_000_000_000_000)
    rec = McapRecorder(tmp_path / "g.mcap")
    RecordingSink(rec, tb).pose_graph(tb.ns(10.0), snap)
    rec.close()
    got = {t: m for t, _, _, m in read_mcap(tmp_path / "g.mcap")}
    path = got["/pose_graph/path"]
    assert len(path.poses) == len(keys)
    np.testing.assert_allclose([p.pose.position.x for p in path.poses], snap.poses[:, 0])
    np.testing.assert_allclose([M.yaw_of(p.pose.orientation) for p in path.poses], snap.poses[:, 2], atol=1e-9)
    grid = got["/map/corrected"]
    assert grid.info.width == snap.grid.grid.shape[1] and (grid.data > 65).sum() > 100


def test_processor_hands_key_scans_to_the_worker_and_reports_corrected_poses(tmp_path):
    proc = MappingProcessor(MappingConfig(loop_closure=True, deskew=False))
    tb = M.TimeBase(offset_ns=0)
    rec = McapRecorder(tmp_path / "p.mcap")
    sink = RecordingSink(rec, tb)
    try:
        for i in range(6):
            r = proc.process(make_scan(0.1 * i, seq=i), [make_odom(0.1 * i, x=0.06 * i)])
            assert r.corrected_pose is not None
            # no closure: no correction, and the front end's covariance
            np.testing.assert_allclose(r.corrected_pose.pose, r.estimate.pose, atol=1e-9)
            np.testing.assert_allclose(r.corrected_pose.covariance, r.estimate.covariance, atol=1e-15)
            sink.result(r)
        rec.close()
        got = [m for t, _, _, m in read_mcap(tmp_path / "p.mcap") if t == "/pose/corrected"]
        assert len(got) == 6
        np.testing.assert_allclose(M.cov3(got[-1].pose.covariance), r.corrected_pose.covariance, atol=1e-12)
        snap = proc.finish_graph()
        assert len(snap.stamps) == proc.estimator.stats.keyframes
        assert snap.glass is not None and snap.glass.grid is snap.grid.grid  # the glass map rebuilt too
        assert not proc.graph._alive()  # the worker is stopped with the run: no process left behind
    finally:
        proc.graph.close()
    assert MappingProcessor(MappingConfig()).finish_graph() is None


def _loop_keys():
    truth = _route([(-8.5, -4.5), (8.5, -4.5), (8.5, 4.5), (-8.5, 4.5), (-8.5, -4.5), (0.0, -4.5)])
    return _keys(_ring(), truth, yaw_bias=np.radians(0.012))


def test_maps_published_during_the_run_do_not_change_the_final_graph():
    keys = _loop_keys()
    inline = GraphBackEnd(BackEndConfig())
    for k in keys:
        inline.add(k)
    assert inline.closures
    w = GraphWorker(BackEndConfig(), rebuild_period=0.0)  # corrected maps after closures, once caught up
    try:
        for i, k in enumerate(keys):
            w.submit(k)
            while i % 10 == 9 and w.pending:  # let it catch up now and then, as a live run does
                time.sleep(0.01)
        deadline = time.monotonic() + 60.0
        while w.snapshot().version < 1 and time.monotonic() < deadline:  # a rebuild goes on between key scans
            time.sleep(0.01)
        snap = w.finish(timeout=120.0)
    finally:
        w.close()
    assert snap.version >= 2 and snap.closures == len(inline.closures)  # maps published before the final ones
    assert [(c.anchor, c.node) for c in snap.accepted] == [(c.anchor, c.node) for c in inline.closures]
    np.testing.assert_array_equal(snap.poses, inline.poses())
    assert w.busy_time > 0 and w.pending == 0


def test_in_process_worker_gives_the_same_graph():
    keys = _short_keys()[:20]
    out = []
    for in_process in (False, True):
        w = GraphWorker(BackEndConfig(), in_process=in_process)
        try:
            for k in keys:
                w.submit(k)
            out.append(w.finish())
        finally:
            w.close()
        assert w.in_process == in_process
    np.testing.assert_array_equal(out[0].poses, out[1].poses)
    np.testing.assert_array_equal(out[0].grid.probability(), out[1].grid.probability())


def test_a_killed_worker_process_is_reported_not_waited_for():
    w = GraphWorker(BackEndConfig())
    try:
        w.submit(_short_keys()[0])
        os.kill(w._process.pid, signal.SIGKILL)
        t = time.monotonic()
        with pytest.raises(GraphWorkerError, match="ended unexpectedly"):
            w.finish(timeout=30.0)
        assert time.monotonic() - t < 10.0
        w.submit(_short_keys()[1])  # dropped, no error: the scans go on without the back end
    finally:
        w.close()


def test_an_error_in_the_back_end_is_reported_with_its_cause():
    keys = _short_keys()[:3]
    bad = replace(keys[1], pose=np.zeros(2))  # not a pose
    w = GraphWorker(BackEndConfig())
    try:
        for k in (keys[0], bad, keys[2]):
            w.submit(k)
        with pytest.raises(GraphWorkerError, match="failed"):
            w.finish(timeout=30.0)
    finally:
        w.close()
    assert w._process.exitcode == 0  # it still stopped cleanly when asked


def test_close_stops_the_worker_process():
    w = GraphWorker(BackEndConfig())
    for k in _short_keys()[:5]:
        w.submit(k)
    w.close()
    assert not w._process.is_alive() and w._process.exitcode == 0


def test_bench_takes_the_loop_closure_setting():
    from runtime.cli import _config, build_parser, cmd_bench

    args = build_parser().parse_args(["bench", "--duration", "5", "--mapping.loop_closure", "true"])
    assert args.func is cmd_bench and _config(args).mapping.loop_closure
    assert not _config(build_parser().parse_args(["bench"])).mapping.loop_closure


def test_key_scans_travel_without_intensities_and_echoes():
    from glassmap.types import Scan
    from runtime.graph_worker import compact

    k = _short_keys()[0]
    n = k.ranges.shape[0]
    scan = Scan(stamp=k.stamp, ranges=k.ranges, intensities=np.ones(n), echoes=np.full((n, 2), np.nan),
                echo_intensities=np.zeros((n, 2)))
    c = compact(replace(k, scan=scan, p_glass=np.full(n, 0.5)))
    assert c.scan.intensities is None and c.scan.echoes is None and c.scan.echo_intensities is None
    assert c.scan.ranges is scan.ranges and c.p_glass is not None and c.pose is k.pose
    assert compact(k) is k  # no raw scan: nothing to strip


def test_map_worker_builds_the_graph_messages_the_sink_would():
    import asyncio

    from runtime.map_worker import MapWorker

    keys = _short_keys()[:12]
    snap = _final_snapshot(keys, mapper=None)
    tb = M.TimeBase(offset_ns=1_700_000_000_000_000_000)

    async def build():
        mw = MapWorker()
        try:
            return await mw.graph_messages(snap, tb.ns(10.0), "map", tb)
        finally:
            mw.shutdown()

    msgs = asyncio.run(build())
    assert msgs == graph_messages(snap, tb.ns(10.0), "map", tb)  # the same bytes in the worker process
    assert [t for t, _ in msgs] == ["/pose_graph/path", "/map/corrected"]  # no glass map without a mapper
    path = M.typestore().deserialize_cdr(msgs[0][1], M.TOPICS["/pose_graph/path"])
    assert len(path.poses) == len(keys) and path.poses[3].header.stamp.sec == tb.ns(keys[3].stamp) // 10**9
