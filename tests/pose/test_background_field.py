"""The likelihood-field rebuild in the worker thread gives exactly the estimates of the inline rebuild."""

import pickle

import numpy as np
import pytest

from glassmap.pose import EstimatorConfig, PoseEstimator
from glassmap.pose.motion import compose
from glassmap.types import Odometry
from tests.pose.synth import make_scan, room_with_corner


def _drive(background: bool, incremental: bool = True) -> tuple[np.ndarray, PoseEstimator]:
    """1.6 m through a room, the field re-centred every 0.2 m (incremental) or rebuilt every 2 key scans."""
    segs = room_with_corner()
    mount = np.array([0.1, 0.0, 0.0])
    est = PoseEstimator(EstimatorConfig(laser_mount=tuple(mount), initial_pose=(-1.5, -1.0, 0.0),
                                        field_incremental=incremental, field_recentre=0.2, field_refresh_scans=2,
                                        background_field=background))
    rng = np.random.default_rng(3)
    true, odom, dt, poses = np.array([-1.5, -1.0, 0.0]), np.zeros(3), 0.025, []
    for k in range(160):
        v, w = 0.4, (0.6 if 60 <= k < 120 else 0.0)
        step = np.array([v * dt, 0.0, w * dt])
        if k > 0:
            true = compose(true, step)
            odom = compose(odom, np.array([1.03 * step[0], 0.0, 1.05 * step[2]]))
        est.predict(Odometry(stamp=k * dt, x=odom[0], y=odom[1], yaw=odom[2], v=v, omega=w))
        poses.append(est.update(make_scan(segs, compose(true, mount), stamp=k * dt, noise=0.01, rng=rng)).pose)
    return np.array(poses), est


@pytest.mark.parametrize("incremental", [True, False])
def test_background_rebuild_gives_the_inline_estimates_exactly(incremental):
    inline, est_inline = _drive(False, incremental)
    background, est_bg = _drive(True, incremental)
    assert est_bg.stats.field_rebuilds == est_inline.stats.field_rebuilds >= 5
    assert np.array_equal(inline, background)
    assert (est_bg.stats.field_updates > 30) == incremental


def test_an_estimator_with_a_pending_rebuild_pickles():
    _, est = _drive(True)
    clone = pickle.loads(pickle.dumps(est))
    assert clone.field.ready and clone.stats == est.stats
