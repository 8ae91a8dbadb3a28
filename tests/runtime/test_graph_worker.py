"""The pose-graph worker: same graph as the back end run in line (so a replay reproduces it), a corrected
grid at the end, the processor's hook, and the recorded trajectory + corrected map."""

import numpy as np

from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from runtime import messages as M
from runtime.config import MappingConfig
from runtime.graph_worker import GraphWorker
from runtime.processor import MappingProcessor
from runtime.recorder import McapRecorder, read_mcap
from runtime.sink import RecordingSink
from tests.pose.test_loop_closure import _keys, _ring, _route
from tests.runtime.factories import make_odom, make_scan


def _short_keys():
    truth = _route([(-8.5, -4.5), (0.0, -4.5)])
    return _keys(_ring(), truth, yaw_bias=0.001)


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
    np.testing.assert_allclose(w.correction(), inline.correction(), atol=1e-9)


def test_sink_records_the_optimised_path_and_the_corrected_map(tmp_path):
    keys = _short_keys()[:12]
    w = GraphWorker(BackEndConfig())
    try:
        for k in keys:
            w.submit(k)
        snap = w.finish()
    finally:
        w.close()
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


def test_processor_hands_key_scans_to_the_worker_and_reports_corrected_poses():
    proc = MappingProcessor(MappingConfig(loop_closure=True, deskew=False))
    try:
        for i in range(6):
            r = proc.process(make_scan(0.1 * i, seq=i), [make_odom(0.1 * i, x=0.06 * i)])
            assert r.corrected_pose is not None
            np.testing.assert_allclose(r.corrected_pose, r.estimate.pose, atol=1e-9)  # no closure: no correction
        snap = proc.finish_graph()
        assert len(snap.stamps) == proc.estimator.stats.keyframes
        assert snap.glass is not None and snap.glass.grid is snap.grid.grid  # the glass map rebuilt too
    finally:
        proc.graph.close()
    assert MappingProcessor(MappingConfig()).finish_graph() is None
