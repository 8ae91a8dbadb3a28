"""A driven robot is held at rest while the pose estimator reports its track lost; it drives on when the track
recovers, and the run stops, with the reason, when it does not recover within ``base.lost_hold`` or when the
reported position uncertainty exceeds ``base.max_sigma``."""

import asyncio
from types import SimpleNamespace

import numpy as np

from glassmap.pose.estimator import EstimatorStats
from glassmap.types import LaserGeometry, PoseEstimate, Scan
from runtime.app import Runtime
from runtime.config import BaseConfig, RuntimeConfig
from runtime.pipeline import ScanResult
from runtime.shutdown import StopRequest


def _result(status: str, stamp: float = 12.5, sigma: float = 0.01, corrected_sigma: float | None = None
            ) -> ScanResult:
    """A result at ``stamp`` whose estimate has position standard deviation ``sigma`` (m) along its widest
    direction (and, if given, a pose-graph-corrected estimate of ``corrected_sigma``)."""
    scan = Scan(stamp=stamp, ranges=np.ones(LaserGeometry().n_beams), intensities=None, geometry=LaserGeometry())

    def cov(s):  # widest along the diagonal x = y, 1 cm across
        r = np.array([[1.0, -1.0], [1.0, 1.0]]) / np.sqrt(2.0)
        c = np.diag([1e-4, 1e-4, 1e-4])
        c[:2, :2] = r @ np.diag([s ** 2, 1e-4]) @ r.T
        return c

    corrected = None if corrected_sigma is None else PoseEstimate(stamp, 0.0, 0.0, 0.0, cov(corrected_sigma))
    return ScanResult(scan=scan, estimate=PoseEstimate(stamp, 0.0, 0.0, 0.0, cov(sigma), status=status),
                      laser_pose=np.zeros(3), p_glass=None, corrected_pose=corrected)


class _Base:
    """Records the velocity commands (m/s, rad/s) the runtime sends."""

    def __init__(self) -> None:
        self.commands: list[tuple[float, float]] = []

    async def set_velocity(self, v: float, omega: float) -> None:
        self.commands.append((v, omega))


def _runtime(driven: bool, lost_hold: float = 5.0, time_scale: float = 1.0, max_sigma: float = 1.0
             ) -> tuple[Runtime, StopRequest]:
    stats = EstimatorStats(status="lost", status_reason="5 consecutive scan matches disagree")
    processor = SimpleNamespace(estimator=SimpleNamespace(stats=stats))

    async def driver(rt):  # never called here
        return None

    stop = StopRequest()
    rt = Runtime(RuntimeConfig(base=BaseConfig(lost_hold=lost_hold, max_sigma=max_sigma)), processor=processor,
                 pioneer_options={"time_scale": time_scale}, driver=driver if driven else None, stop=stop)
    rt.base = _Base()
    return rt, stop


def test_a_lost_track_holds_the_robot_at_rest_until_it_recovers():
    async def go():
        rt, stop = _runtime(driven=True)
        rt._on_result(_result("degraded", 10.0))
        await rt.command_velocity(0.4, 0.1)
        rt._on_result(_result("lost", 11.0))
        await asyncio.sleep(0)  # the immediate zero command
        await rt.command_velocity(0.4, 0.1)  # the driver's next command, while held
        rt._on_result(_result("lost", 14.0))
        assert not stop.is_set()
        rt._on_result(_result("ok", 14.5))
        await rt.command_velocity(0.4, 0.1)
        assert rt.base.commands == [(0.4, 0.1), (0.0, 0.0), (0.0, 0.0), (0.4, 0.1)]
        assert not stop.is_set()
        assert rt.summary.lost_holds == 1 and abs(rt.summary.lost_held_s - 3.5) < 1e-9

    asyncio.run(go())


def test_a_track_not_recovered_within_the_hold_stops_the_run_with_the_reason():
    async def go():
        rt, stop = _runtime(driven=True, lost_hold=2.0)
        rt._on_result(_result("lost", 11.0))
        rt._on_result(_result("lost", 12.9))
        assert not stop.is_set()
        rt._on_result(_result("lost", 13.0))
        assert stop.is_set() and "pose estimate lost" in stop.reason and "disagree" in stop.reason
        assert "not recovered within 2 s" in stop.reason

    asyncio.run(go())


def test_the_hold_is_in_the_robots_time_when_the_devices_run_faster():
    async def go():
        rt, stop = _runtime(driven=True, lost_hold=2.0, time_scale=4.0)  # 2 s of the robot's = 0.5 s here
        rt._on_result(_result("lost", 11.0))
        rt._on_result(_result("lost", 11.4))
        assert not stop.is_set()
        rt._on_result(_result("lost", 11.5))
        assert stop.is_set()

    asyncio.run(go())


def test_with_no_hold_a_lost_track_stops_a_driven_robot_at_once():
    async def go():
        rt, stop = _runtime(driven=True, lost_hold=0.0)
        rt._on_result(_result("degraded"))
        assert not stop.is_set()
        rt._on_result(_result("lost"))
        assert stop.is_set() and "pose estimate lost" in stop.reason and "disagree" in stop.reason

    asyncio.run(go())


def test_without_a_driver_a_lost_track_does_not_end_the_run():
    async def go():
        rt, stop = _runtime(driven=False)
        rt._on_result(_result("lost", 11.0))
        rt._on_result(_result("lost", 30.0))
        assert not stop.is_set()

    asyncio.run(go())


def test_a_driven_run_stops_when_the_position_is_too_uncertain_to_follow_a_route():
    async def go():
        rt, stop = _runtime(driven=True, max_sigma=1.0)
        rt._on_result(_result("ok", 10.0, sigma=0.9))
        assert not stop.is_set()
        rt._on_result(_result("ok", 10.1, sigma=1.1))  # 1.1 m along the diagonal: x and y alone are 0.78 m
        await asyncio.sleep(0)
        assert stop.is_set() and "too uncertain" in stop.reason and "1.10 m > base.max_sigma 1 m" in stop.reason
        assert rt.base.commands == [(0.0, 0.0)]

    asyncio.run(go())


def test_with_loop_closure_the_corrected_estimate_is_the_one_judged():
    async def go():
        rt, stop = _runtime(driven=True, max_sigma=1.0)
        rt._on_result(_result("ok", 10.0, sigma=2.0, corrected_sigma=0.2))  # the graph's closures narrowed it
        assert not stop.is_set()
        rt._on_result(_result("ok", 10.1, sigma=0.2, corrected_sigma=1.5))
        assert stop.is_set()

    asyncio.run(go())


def test_max_sigma_0_never_stops_and_an_undriven_run_is_not_stopped():
    async def go():
        for driven, limit in ((True, 0.0), (False, 1.0)):
            rt, stop = _runtime(driven=driven, max_sigma=limit)
            rt._on_result(_result("ok", 10.0, sigma=5.0))
            assert not stop.is_set()

    asyncio.run(go())
