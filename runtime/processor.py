"""The per-scan work of the runtime: pose estimation, then the glass path, on one shared occupancy grid.

:class:`MappingProcessor` runs in the processing thread (see :mod:`runtime.pipeline`); it is also used
directly (no event loop) by replay and bench.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from glassmap.types import Odometry, Scan
from runtime.config import MappingConfig
from runtime.pipeline import ScanResult
from runtime.tuning import one_blas_thread


class MappingProcessor:
    """PoseEstimator (odometry + scan matching) then GlassMapper on the same occupancy grid.

    ``mapping.occupancy_update`` chooses who integrates the scan at the corrected pose: the mapper (default;
    its update keeps cells hit by glass-classified beams occupied and protects them from being cleared by
    beams passing through the glass, so glass walls stay in the map) or the estimator (plain update; the
    mapper then runs with ``update_occupancy=False``). Either way the integration
    happens once per key scan, after matching, at the corrected laser pose. Key scans are chosen by the
    estimator's motion filter (``EstimatorConfig.keyframe_*``: moved >= 5 cm or turned >= 2 deg since the
    last key scan, or 20 scans since it); every scan still gets a pose + covariance and p(glass) per beam.
    Every scan's glass-classified beams keep their cells occupied (glass is seen only near normal incidence,
    often for a few scans); ``mapping.glass_scans`` chooses the scans whose p(glass) is registered onto the
    glass map: the key scans (default), at the pose their match gave, or every scan, most of them placed by
    odometry since the last match. The registration sigma comes from ``mapping.registration_sigma``
    (:func:`~glassmap.pose.corrected.online_sigma`: by default the pose's covariance relative to the map it
    registers on)."""

    def __init__(self, mapping: MappingConfig, *, estimator_config=None, mapper_config=None) -> None:
        from dataclasses import replace

        from glassmap.mapping import GlassMapper, MapperConfig
        from glassmap.pose import EstimatorConfig, PoseEstimator
        from glassmap.pose.corrected import online_sigma

        ecfg = estimator_config or EstimatorConfig()
        ecfg = replace(ecfg, laser_mount=(mapping.laser_x, mapping.laser_y, mapping.laser_yaw),
                       glass_weighting=mapping.glass_weighting, deskew=mapping.deskew,
                       keyframe_distance=mapping.keyframe_distance,
                       keyframe_angle=math.radians(mapping.keyframe_angle_deg),
                       keyframe_max_scans=mapping.keyframe_max_scans,
                       integrate=mapping.occupancy_update == "estimator",
                       occupancy=replace(ecfg.occupancy, max_free_range=mapping.max_free_range,
                                         no_return_range=mapping.no_return_range,
                                         hit_margin=mapping.hit_margin, surface_margin=mapping.surface_margin),
                       initial_pose=(mapping.initial_x, mapping.initial_y, mapping.initial_yaw))
        self.estimator = PoseEstimator(ecfg)
        mcfg = mapper_config or MapperConfig(registration=mapping.registration, window=mapping.window,
                                             decay_ref=mapping.decay_reference, aggregation=mapping.aggregation,
                                             visibility=mapping.visibility,
                                             weights=mapping.classifier_weights or None)
        self.mapper = GlassMapper(occupancy=self.estimator.occupancy, config=mcfg)
        self.mapper_integrates = mapping.occupancy_update == "mapper"
        self.sigma_source = mapping.registration_sigma
        self.glass_every_scan = mapping.glass_scans == "all"
        self._online_sigma = online_sigma  # glassmap.pose is imported lazily in this module
        self.graph = None  # the pose-graph worker (mapping.loop_closure)
        if mapping.loop_closure:
            from glassmap.pose.backend import BackEndConfig
            from runtime.graph_worker import GraphWorker

            backend = BackEndConfig()
            self.graph = GraphWorker(backend, ecfg.likelihood.sigma_hit, ecfg.occupancy, mapper=mcfg)
            self._backend_config = backend
        self.graph_lag = 0  # key scans the pose graph had not taken in when the last corrected estimate was made
        self.latest_odom: Odometry | None = None
        self.scans = 0
        one_blas_thread()  # small products in one processing thread (runtime.tuning)

    @property
    def wants_echoes(self) -> bool:
        """The glass classifier reads multi-echo scans (the laser should stream NE)."""
        return bool(getattr(self.mapper.classifier, "uses_echoes", False))

    def warm_up(self) -> None:
        """Run the glass path once on a synthetic scan (a room of 4 x 6 m) on a scratch grid, without
        touching the maps or the pose, and decode a multi-echo laser message: the first network call and
        the first call of each compiled kernel cost tens of milliseconds (seconds the first time on a
        machine, when they compile), which would otherwise delay the first real scans."""
        from drivers.hokuyo.scip import warm_up as warm_up_decoders
        from glassmap.pose.matcher import warm_up as warm_up_matcher
        from glassmap.types import LaserGeometry
        from runtime.messages_jit import warm_up as warm_up_last_echo

        warm_up_matcher()  # the scan matcher's compiled lookups, which the first key scan would load
        warm_up_last_echo()  # the event loop's, which the first multi-echo scan would load
        # the laser decoder's compiled paths (multi-echo data, millimetres to metres), which the event loop
        # would load at the first scan
        warm_up_decoders()
        geo = LaserGeometry()
        a = geo.angles
        with np.errstate(divide="ignore"):
            r = np.minimum(np.abs(2.0 / np.sin(a)), np.abs(3.0 / np.cos(a)))
        pane = (a > 0.3) & (a < 0.9) & (np.arange(a.size) % 2 == 1)
        r[pane] *= 0.6  # a pane seen on every other beam: the line extractor's second pass runs too
        echoes = np.full((a.shape[0], 1), np.nan) if self.wants_echoes else None  # as the laser will send
        self.mapper.warm_up(Scan(stamp=0.0, ranges=r, intensities=np.full(a.shape, 3000.0), geometry=geo,
                                  echoes=echoes, echo_intensities=None if echoes is None else np.zeros_like(echoes)))

    def process(self, scan: Scan, odometry: list[Odometry]) -> ScanResult:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        for o in odometry:
            self.estimator.predict(o)
            if self.latest_odom is None or o.stamp >= self.latest_odom.stamp:
                self.latest_odom = o
        est = self.estimator.update(scan)
        t1 = time.perf_counter()
        laser_pose = self.estimator.laser_pose(est)
        key = self.estimator.stats.last_keyframe
        register = key or self.glass_every_scan
        sigma = self._online_sigma(self.estimator, est, scan.ranges, self.sigma_source) if register else None
        beams = self.mapper.process(scan, laser_pose, sigma, update_occupancy=self.mapper_integrates and key,
                                    register=register)
        t2 = time.perf_counter()
        corrected = None
        if self.graph is not None:
            if key and self.estimator.last_key_scan is not None:
                self.graph.submit(replace(self.estimator.last_key_scan, scan=scan, p_glass=beams.p_glass,
                                              incidence=beams.incidence))
            from glassmap.pose.backend import corrected_estimate  # glassmap.pose is imported lazily here

            correction, self.graph_lag = self.graph.latest_correction()
            corrected = corrected_estimate(est, correction, self._backend_config,
                                           self.estimator.off_chain_covariance())
        self.scans += 1
        st = self.estimator.stats
        timings = {"pose": st.t_core, "likelihood_field": st.t_field, "occupancy": st.t_integrate,
                   "pose_total": t1 - t0, "glass": t2 - t1, "total": t2 - t0, "cpu": time.thread_time() - c0}
        return ScanResult(scan=scan, estimate=est, laser_pose=laser_pose, p_glass=beams.p_glass,
                          odom=self.latest_odom, timings=timings, corrected_pose=corrected)

    def finish_graph(self, timeout: float = 60.0):
        """Wait for the pose-graph worker to take in every key scan, return its final
        :class:`~runtime.graph_worker.GraphSnapshot` (optimised trajectory + corrected grid) and stop the
        worker, so that its process does not outlive the run; None without loop closure."""
        if self.graph is None:
            return None
        try:
            return self.graph.finish(timeout)
        finally:
            self.graph.close()

    def copy_maps(self):
        """Copies of the maps (a picklable :class:`~glassmap.mapping.MapCopy`) to publish or export elsewhere:
        the copy is a ~1 ms memcpy in the processing thread; the conversions and the file writing then do not
        hold up the scans."""
        return self.mapper.copy_maps()
