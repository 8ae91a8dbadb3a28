"""A driven robot is stopped, with the reason, as soon as the pose estimator reports its track lost."""

import asyncio
from types import SimpleNamespace

import numpy as np

from glassmap.pose.estimator import EstimatorStats
from glassmap.types import LaserGeometry, PoseEstimate, Scan
from runtime.app import Runtime
from runtime.config import RuntimeConfig
from runtime.pipeline import ScanResult
from runtime.shutdown import StopRequest


def _result(status: str) -> ScanResult:
    scan = Scan(stamp=12.5, ranges=np.ones(LaserGeometry().n_beams), intensities=None, geometry=LaserGeometry())
    return ScanResult(scan=scan, estimate=PoseEstimate(12.5, 0.0, 0.0, 0.0, np.eye(3) * 1e-4, status=status),
                      laser_pose=np.zeros(3), p_glass=None)


def _runtime(driven: bool) -> tuple[Runtime, StopRequest]:
    stats = EstimatorStats(status="lost", status_reason="5 consecutive scan matches disagree")
    processor = SimpleNamespace(estimator=SimpleNamespace(stats=stats))

    async def driver(rt):  # never called here
        return None

    stop = StopRequest()
    rt = Runtime(RuntimeConfig(), processor=processor, driver=driver if driven else None, stop=stop)
    return rt, stop


def test_a_lost_track_stops_a_driven_robot_with_the_reason():
    async def go():
        rt, stop = _runtime(driven=True)
        rt._on_result(_result("degraded"))
        assert not stop.is_set()
        rt._on_result(_result("lost"))
        assert stop.is_set() and "pose estimate lost" in stop.reason and "disagree" in stop.reason

    asyncio.run(go())


def test_without_a_driver_a_lost_track_does_not_end_the_run():
    async def go():
        rt, stop = _runtime(driven=False)
        rt._on_result(_result("lost"))
        assert not stop.is_set()

    asyncio.run(go())
