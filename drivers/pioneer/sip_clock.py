"""SIP arrival times -> de-jittered host stamps on the controller's fixed SIP cycle (sans-IO).

A SIP carries no clock, but ARCOS/P2OS sends one every SIP cycle (``sip_cycle`` in CONFIG, 100 ms by
default; robot seconds, host seconds divided by the client's time_scale). SIP k is therefore sent at
host time c + k P and arrives at c + L + k P + jitter with jitter >= 0 (a busy host reads late, never
early), so the lower envelope of (k, arrival) is the clock (``drivers.clock.ClockMapper``, which also
fits P, so time_scale is only its first guess). A stamp is the envelope at k: the send time plus the
fixed latency L, which cannot be told apart from it without a clock on the robot.

The index k follows the cycle, not the packet count: a SIP lost on the link (bad checksum, a pty hiccup)
makes every later arrival at least a cycle late, so SIPs that stay more than half a cycle late for a few
cycles of arrival time are a gap and k skips it; a burst of SIPs that a stalled host reads together is
late by many cycles but only until the stall ends, so it does not move k. A SIP more than half a cycle
before the envelope means k ran ahead, and k steps back. Until the envelope has a slope a SIP is
stamped with its arrival. Stamps never exceed the arrival and never go back.
"""

from __future__ import annotations

import math

from drivers.clock import ClockMapper

DEFAULT_SIP_CYCLE = 0.1  # s (robot time): the ARCOS/P2OS default


class SipClock:
    """Stamps SIPs of one link: feed each SIP's arrival (host s) to :meth:`stamp`; :meth:`reset` per link.

    cycle: SIP cycle (robot s); time_scale: robot seconds per host second, the first guess of the rate;
    gap_cycles: cycles of arrival time SIPs must stay late before a gap is accepted.
    """

    def __init__(self, cycle: float = DEFAULT_SIP_CYCLE, *, time_scale: float = 1.0,
                 gap_cycles: float = 3.0) -> None:
        if cycle <= 0 or time_scale <= 0 or gap_cycles <= 0:
            raise ValueError(f"SipClock: cycle, time_scale and gap_cycles must be > 0, got {cycle}, "
                             f"{time_scale}, {gap_cycles}")
        self.time_scale = float(time_scale)
        self.gap_cycles = float(gap_cycles)
        self.gaps = 0  # SIPs found missing (index skipped)
        self.rewinds = 0  # times the index ran ahead of the envelope and stepped back
        self.cycle = float(cycle)
        self.reset()

    @property
    def period(self) -> float:
        """Host seconds per SIP: the fitted one once there is a slope, else cycle / time_scale."""
        return self._mapper.slope * self._guess

    def set_cycle(self, cycle: float) -> None:
        """The SIP cycle from the CONFIG packet (robot s); a change starts over."""
        if cycle > 0 and not math.isclose(cycle, self.cycle):
            self.cycle = float(cycle)
            self.reset()

    def reset(self) -> None:
        """A new link (handshake): the controller's cycle restarts, so does the clock."""
        self._guess = self.cycle / self.time_scale
        self._mapper = ClockMapper(block=8, window=40, jump_tolerance=math.inf, default_latency=0.0)
        self._index = -1
        self._last: float | None = None
        self._late_since: float | None = None  # arrival of the first SIP of the current run of late ones
        self._late_count = 0
        self._late_min = math.inf

    def stamp(self, arrival: float) -> float:
        """Host stamp (s) of the next SIP, which arrived at host time ``arrival`` (s)."""
        k = self._index + 1
        if self._mapper.fitted:
            k += self._correction(k, arrival)
        self._index = k
        t = min(self._mapper.observe(k * self._guess, arrival), arrival)
        if self._last is not None:
            t = max(t, self._last)
        self._last = t
        return t

    def _correction(self, k: int, arrival: float) -> int:
        """Cycles to add to the counted index ``k``: > 0 after a confirmed gap, < 0 if it ran ahead."""
        period = self.period
        late = arrival - self._mapper.host_time(k * self._guess)
        if late < -0.5 * period:
            self.rewinds += 1
            self._late_since = None
            return -round(-late / period)
        if late < 0.5 * period:
            self._late_since = None
            return 0
        if self._late_since is None:
            self._late_since, self._late_count, self._late_min = arrival, 0, math.inf
        self._late_count += 1
        self._late_min = min(self._late_min, late)
        if self._late_count >= 3 and arrival - self._late_since >= self.gap_cycles * period:
            skip = round(self._late_min / period)
            self.gaps += skip
            self._late_since = None
            return skip
        return 0


__all__ = ["DEFAULT_SIP_CYCLE", "SipClock"]
