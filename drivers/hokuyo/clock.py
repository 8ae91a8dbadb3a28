"""SCIP sensor stamps: 24-bit millisecond unwrapping (the sensor -> host clock model is drivers/clock.py)."""

from __future__ import annotations

TIMESTAMP_MOD = 1 << 24


class TimestampUnwrapper:
    """Unwrap 24-bit millisecond stamps with the half-range rule (a step back of less than half the
    range is a step back, not a wrap)."""

    def __init__(self) -> None:
        self._last: int | None = None
        self._total = 0

    def reset(self) -> None:
        self._last = None
        self._total = 0

    def unwrap(self, raw_ms: int) -> int:
        """Unwrapped milliseconds for the next raw 24-bit stamp."""
        raw_ms %= TIMESTAMP_MOD
        if self._last is None:
            self._total = raw_ms
        else:
            d = (raw_ms - self._last) % TIMESTAMP_MOD
            if d >= TIMESTAMP_MOD // 2:
                d -= TIMESTAMP_MOD
            self._total += d
        self._last = raw_ms
        return self._total
