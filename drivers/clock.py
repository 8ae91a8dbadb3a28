"""Device clock -> host clock from arrival times: offset, drift, jumps, optional round-trip anchor (sans-IO).

Shared by the Hokuyo (SCIP scan stamps and TM1 round trips) and the Pioneer (SIP indices on the fixed SIP
cycle, drivers/pioneer/sip_clock.py).

Model: host(s) = a + b * s for sensor time s (seconds, unwrapped). A scan stamped s (its first step)
arrives at the host at host(s) + L + jitter, where L (host seconds) is the fixed part of the latency
(the sweep itself plus transmission) and jitter >= 0. The *lower envelope* of (s, arrival) pairs is
therefore the line a + L + b * s: it is the lower envelope of the minimum arrivals of consecutive blocks
of scans (a line below all of them, as close as it can be: late scans never pull the clock), fitted once
there are four blocks (until then only the offset moves).
L comes from the TM1 round trips (the minimum-round-trip sample gives host(s) at one instant); without
them L defaults to one scan time. A sensor clock jump (a stamp far from the line) is confirmed by the
next few scans before the model is re-anchored; a single odd stamp is only counted as an outlier.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RoundTrip:
    """One TM1 exchange: host send / receive times (s) and the sensor time it returned (s)."""

    host_sent: float
    host_received: float
    sensor: float

    @property
    def rtt(self) -> float:
        return self.host_received - self.host_sent


class ClockMapper:
    """Maps unwrapped sensor seconds to host seconds; feed it TM1 round trips and scan arrivals.

    block: scans per envelope block; window: blocks kept for the fit (block * window scans);
    jump_tolerance: host seconds a stamp may sit off the line before it is a jump candidate;
    confirm: scans that must agree with a jump before it is accepted; default_latency: L without TM1.
    """

    def __init__(self, *, block: int = 8, window: int = 40, jump_tolerance: float = 0.25, confirm: int = 3,
                 default_latency: float = 0.025) -> None:
        if block < 1 or window < 2 or confirm < 1 or jump_tolerance <= 0:
            raise ValueError("ClockMapper: block >= 1, window >= 2, confirm >= 1, jump_tolerance > 0")
        self.block, self.window, self.jump_tolerance, self.confirm = block, window, jump_tolerance, confirm
        self.default_latency = default_latency
        self.anchor: RoundTrip | None = None
        self.latency: float | None = None
        self.slope = 1.0  # host seconds per sensor second
        self.intercept: float | None = None  # of the arrival envelope: arrival_min(s) = intercept + slope*s
        self.jumps = 0
        self.outliers = 0
        self._blocks: deque[tuple[float, float]] = deque(maxlen=window)  # (sensor s, min arrival)
        self._cur: list[tuple[float, float]] = []
        self._candidates: list[tuple[float, float]] = []
        self._have_slope = False  # a fit over >= 4 blocks has happened (kept across clock jumps)

    @property
    def fitted(self) -> bool:
        """A slope has been fitted (over at least four blocks): host_time follows the envelope line."""
        return self._have_slope

    # -- TM1 ------------------------------------------------------------------------------------------
    def add_round_trips(self, samples: list[RoundTrip]) -> RoundTrip | None:
        """Use the minimum-round-trip sample as the anchor host(s) = midpoint of its round trip."""
        if not samples:
            return None
        self.anchor = min(samples, key=lambda r: r.rtt)
        self.latency = None
        return self.anchor

    # -- streaming ------------------------------------------------------------------------------------
    def observe(self, sensor: float, arrival: float) -> float:
        """Record a scan stamped ``sensor`` (s) that arrived at ``arrival`` (host s); return its host stamp."""
        if self._have_slope:  # (before, the line's slope is a guess: being off it says nothing yet)
            resid = arrival - (self.intercept + self.slope * sensor)
            if resid < -self.jump_tolerance or resid > 4 * self.jump_tolerance:
                return self._candidate(sensor, arrival)
            self.outliers += len(self._candidates)
            self._candidates.clear()
        self._cur.append((sensor, arrival))
        if len(self._cur) >= self.block:
            s, a = min(self._cur, key=lambda p: p[1] - self.slope * p[0])
            self._blocks.append((s, a))
            self._cur = []
            self._fit()
        return self.host_time(sensor, arrival)

    def host_time(self, sensor: float, arrival: float | None = None) -> float:
        """Host time of sensor time ``sensor`` under the current model (arrival is a fallback).

        Until four blocks have given a slope, a scan is stamped arrival - latency: a few ms of jitter, but no
        error from an unknown clock rate (an emulator running faster than real time has slope != 1)."""
        if self.intercept is not None and self.latency is not None and self._have_slope:
            return self.intercept + self.slope * sensor - self.latency
        if arrival is not None:
            return arrival - (self.latency if self.latency is not None else self.default_latency)
        if self.intercept is not None and self.latency is not None:
            return self.intercept + self.slope * sensor - self.latency
        if self.anchor is not None:
            mid = 0.5 * (self.anchor.host_sent + self.anchor.host_received)
            return mid + (sensor - self.anchor.sensor)
        if self._cur or self._blocks:
            pts = list(self._blocks) + self._cur
            return min(a - s for s, a in pts) + sensor - self.default_latency
        return (arrival if arrival is not None else 0.0) - self.default_latency

    def _fit(self) -> None:
        pts = np.array(self._blocks)
        line = _lower_envelope(pts[:, 0], pts[:, 1]) if pts.shape[0] >= 4 else None
        if line is None:
            # no slope from fewer than four blocks: a late block (a host stall) would tilt the line (with three,
            # a late last block and a steeper line fit equally well), and the scans that follow would look like
            # a sensor clock jump; until then the envelope's lowest block sets the offset
            self.intercept = float(np.min(pts[:, 1] - self.slope * pts[:, 0]))
        else:
            self.intercept, self.slope = line
            self._have_slope = True
        if self.latency is None or (self.anchor is not None and len(self._blocks) <= 6):
            # with a TM1 anchor, L is refined over the first blocks (while the slope settles), then kept
            if self.anchor is not None and self.intercept is not None:
                mid = 0.5 * (self.anchor.host_sent + self.anchor.host_received)
                self.latency = max(self.intercept + self.slope * self.anchor.sensor - mid, 0.0)
            else:
                self.latency = self.default_latency

    def _candidate(self, sensor: float, arrival: float) -> float:
        """A stamp off the line: count it; re-anchor once ``confirm`` scans agree on a new offset."""
        if self._candidates:
            s0, a0 = self._candidates[-1]
            if abs((arrival - a0) - self.slope * (sensor - s0)) > self.jump_tolerance:
                self.outliers += len(self._candidates)
                self._candidates.clear()
        self._candidates.append((sensor, arrival))
        if len(self._candidates) >= self.confirm:
            # A confirmed jump: keep slope and latency, move the envelope to the new stamps.
            pts = self._candidates
            self.intercept = min(a - self.slope * s for s, a in pts)
            self._blocks.clear()
            self._cur = list(pts)
            self._candidates = []
            self.anchor = None  # it belongs to the old timeline; the latency learnt from it is kept
            self.jumps += 1
            return self.host_time(sensor, arrival)
        lat = self.latency if self.latency is not None else self.default_latency
        return arrival - lat


def _lower_envelope(s: np.ndarray, a: np.ndarray) -> tuple[float, float] | None:
    """(c, b) of the line a = c + b s below every point (s_i, a_i) with the least total distance to them
    (the linear program of Moon, Skelly and Towsley 1999 for clock skew from one-way delays: jitter only
    makes arrivals late, so late points never pull the line; its optimum passes through two points).
    None when no line with a positive slope lies below them all, or when no two points have different sensor
    times (a frozen sensor stamp: the caller keeps the arrival-based stamps). Only pairs of points near the lower convex
    hull are tried (both points of a feasible pair lie on it), in the order of all pairs (the same first
    minimum): :func:`drivers.clock_jit.lower_envelope`."""
    from drivers.clock_jit import lower_envelope

    s0, a0 = s[0], a[0]
    # relative times: host times may be epoch seconds, keep the rounding far below a microsecond
    status, c, b = lower_envelope(np.ascontiguousarray(s - s0, dtype=np.float64),
                                  np.ascontiguousarray(a - a0, dtype=np.float64))
    if status <= 0:
        return None
    return float(a0 + c - b * s0), float(b)
