"""SIP arrival times -> de-jittered host stamps on the controller's fixed SIP cycle (sans-IO).

A SIP carries no clock, but ARCOS/P2OS sends one every SIP cycle (``sip_cycle`` in CONFIG, 100 ms by
default; robot seconds, host seconds divided by the client's time_scale). SIP k is therefore sent at
host time c + k P and arrives at c + L + k P + jitter with jitter >= 0 (a busy host reads late, never
early), so the lower envelope of (k, arrival) is the clock (``drivers.clock.ClockMapper``, which also
fits P, so time_scale is only its first guess). A stamp is the envelope at k: the send time plus the
fixed latency L, which cannot be told apart from it without a clock on the robot.

The index k follows the cycle, not the packet count. SIPs read together with more after them
(``queued``) are a burst that a stalled host read late, each a cycle before the next: they take the next
indices, so a stall does not move k. A SIP that arrives at least 0.9 of a cycle after the envelope is
either late or follows lost SIPs (bad checksum, a pty hiccup, a controller that skipped cycles). When the
caller can tell from the SIP's content how many cycles it moves the robot on (``cycles``: its motion since
the previous SIP over the wheel speeds', see ``OdometryTracker.cycles_since_last``), that decides: k skips
the lost SIPs, or the SIP is a late one of the next cycle and is stamped on it. Otherwise (the robot too slow
to tell, when the stamp hardly matters) it is stamped with its arrival, as without the clock, and kept out
of the envelope; if the SIP of the next read is as many whole cycles late, SIPs were lost and k skips them.
A SIP more than half a cycle before the envelope means k ran ahead, and k steps back. Until the envelope
has a slope a SIP is stamped with its arrival. Stamps never exceed the arrival and never go back.
"""

from __future__ import annotations

import math

from drivers.clock import ClockMapper

DEFAULT_SIP_CYCLE = 0.1  # s (robot time): the ARCOS/P2OS default


class SipClock:
    """Stamps SIPs of one link: feed each SIP's arrival (host s) to :meth:`stamp`; :meth:`reset` per link.

    cycle: SIP cycle (robot s); time_scale: robot seconds per host second, the first guess of the rate.
    """

    def __init__(self, cycle: float = DEFAULT_SIP_CYCLE, *, time_scale: float = 1.0) -> None:
        if cycle <= 0 or time_scale <= 0:
            raise ValueError(f"SipClock: cycle and time_scale must be > 0, got {cycle}, {time_scale}")
        self.time_scale = float(time_scale)
        self.gaps = 0  # SIPs found missing (index skipped)
        self.delayed = 0  # SIPs a cycle or more late that their content placed on the next cycle
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
        self._suspect = (0, -math.inf)  # (cycles late, arrival) of a previous SIP too late to tell

    def stamp(self, arrival: float, queued: int = 0, cycles: float | None = None) -> float:
        """Host stamp (s) of the next SIP, which arrived at host time ``arrival`` (s) in a read that held
        ``queued`` more SIPs after it; ``cycles``: how many SIP cycles its content moves the robot on since
        the previous SIP (None: unknown)."""
        self._index += 1
        t = arrival
        if not self._mapper.fitted or self._on_cycle(arrival, queued, cycles):
            t = min(self._mapper.observe(self._index * self._guess, arrival), arrival)
        if self._last is not None:
            t = max(t, self._last)
        self._last = t
        return t

    def _on_cycle(self, arrival: float, queued: int, cycles: float | None) -> bool:
        """Correct the index for lost SIPs or a run ahead; False if this SIP is too late to tell."""
        period = self.period
        late = (arrival - self._mapper.host_time(self._index * self._guess)) / period  # cycles
        if late < -0.5:
            self.rewinds += 1
            self._index -= round(-late)
            return True
        if queued:  # a burst: the host was late, its SIPs each take the next cycle
            return True
        behind = math.floor(late + 0.1)
        suspect, self._suspect = self._suspect, (behind, arrival)
        if behind <= 0:
            return True
        if cycles is not None:  # its content tells: SIPs lost before it (at most as many as it is late), or late
            lost = min(max(round(cycles) - 1, 0), behind)
            self._index += lost
            self.gaps += lost
            self.delayed += lost == 0
            self._suspect = (0, arrival)
            return True
        if behind != suspect[0] or arrival <= suspect[1]:
            return False
        self._index += behind
        self.gaps += behind
        self._suspect = (0, arrival)
        return True


__all__ = ["DEFAULT_SIP_CYCLE", "SipClock"]
