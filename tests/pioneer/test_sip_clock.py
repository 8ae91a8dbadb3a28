"""SIP stamps on the controller's cycle: the lower envelope of arrivals against jitter, bursts, gaps, rates."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.pioneer.sip_clock import SipClock

LATENCY = 0.004  # s: the fixed part of the link delay, inside the envelope


def arrivals(n: int, period: float, rng: np.random.Generator, *, jitter: float, t0: float = 1000.0,
             stalls: tuple[tuple[int, float], ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """(send + latency, arrival) of n SIPs: exponential jitter (mean ``jitter`` s); a stall (k, s) holds the
    reads from SIP k's send for s seconds, then what arrived is read in one burst."""
    sent = t0 + period * np.arange(n) + LATENCY
    arr = sent + rng.exponential(jitter, n)
    for k, dur in stalls:
        end = sent[k] + dur
        arr = np.where((sent >= sent[k]) & (arr < end), end, arr)
    return sent, np.maximum.accumulate(arr)  # one link: packets arrive in order


def stamp_all(clock: SipClock, arr: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """Stamps of the kept SIPs, telling the clock how many more SIPs each one's read held."""
    keep = np.ones(arr.size, bool) if keep is None else keep
    idx = np.flatnonzero(keep)
    out = np.full(arr.size, np.nan)
    for j, i in enumerate(idx):
        out[i] = clock.stamp(float(arr[i]), int(np.sum(arr[idx[j + 1:]] == arr[i])))
    return out


def errors(stamps: np.ndarray, sent: np.ndarray, warmup: int = 40) -> np.ndarray:
    e = stamps[warmup:] - sent[warmup:]
    return np.abs(e[np.isfinite(e)])


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_stamps_follow_the_cycle_far_below_the_jitter(scale):
    period = 0.1 / scale
    sent, arr = arrivals(600, period, np.random.default_rng(1), jitter=0.2 * period)
    stamps = stamp_all(SipClock(time_scale=scale), arr)
    raw = errors(arr, sent)
    err = errors(stamps, sent)
    assert np.percentile(err, 95) < 0.1 * np.percentile(raw, 95)
    assert np.percentile(np.abs(np.diff(stamps[40:]) - period), 95) < 0.1 * np.std(np.diff(arr[40:]))
    assert err.max() <= raw.max()  # a SIP too late to place keeps its arrival


def test_the_rate_is_fitted_when_time_scale_is_not_given():
    """An emulator at 4x with a client told 1x: the envelope's slope finds the 25 ms period."""
    period = 0.025
    sent, arr = arrivals(600, period, np.random.default_rng(2), jitter=0.005)
    clock = SipClock(time_scale=1.0)
    stamps = stamp_all(clock, arr)
    assert clock.period == pytest.approx(period, rel=1e-3)
    assert np.percentile(errors(stamps, sent, warmup=100), 95) < 0.1 * np.percentile(errors(arr, sent), 95)


def test_a_burst_after_a_host_stall_keeps_every_index():
    """Stalls of 1.5, 4.4 and 10.3 cycles: the SIPs read together get their own cycles, and later ones too."""
    period = 0.025
    sent, arr = arrivals(800, period, np.random.default_rng(3), jitter=0.004,
                         stalls=((200, 1.5 * period), (400, 4.4 * period), (600, 10.3 * period)))
    clock = SipClock(time_scale=4.0)
    stamps = stamp_all(clock, arr)
    on_cycle = np.abs(stamps - sent) < 0.1 * period
    assert (arr[600:611] - sent[600:611]).max() > 9 * period  # the burst was late
    burst = np.r_[200:202, 400:405, 600:611]
    assert on_cycle[burst].all() and on_cycle[611:].mean() > 0.98
    assert np.array_equal(stamps[~on_cycle], arr[~on_cycle])  # too late to place: its arrival
    assert clock.gaps == 0 and clock.rewinds == 0


def test_lost_sips_are_skipped_in_the_index():
    period = 0.1
    sent, arr = arrivals(700, period, np.random.default_rng(4), jitter=0.01)
    keep = np.ones(arr.size, bool)
    keep[[300, 450, 451, 452]] = False  # a bad checksum, then a pty hiccup losing three
    clock = SipClock()
    stamps = stamp_all(clock, arr, keep)
    assert clock.gaps == 4
    err = np.abs(stamps - sent)
    late = [301, 453]  # the first SIP after each gap cannot be told from a late one: its arrival
    assert np.allclose(stamps[late], arr[late])
    assert np.nanmax(np.delete(err, late)[40:]) < 0.1 * period


def test_a_reconnect_starts_over():
    period = 0.025
    rng = np.random.default_rng(5)
    sent1, arr1 = arrivals(300, period, rng, jitter=0.005)
    sent2, arr2 = arrivals(300, period, rng, jitter=0.005, t0=float(arr1[-1]) + 2.013)  # another phase
    clock = SipClock(time_scale=4.0)
    stamp_all(clock, arr1)
    clock.reset()
    stamps = stamp_all(clock, arr2)
    assert np.array_equal(stamps[:31], arr2[:31])  # the first SIPs of a link: their arrival, as before
    assert np.percentile(errors(stamps, sent2), 95) < 0.1 * np.percentile(errors(arr2, sent2), 95)


def test_a_changed_sip_cycle_from_config_starts_over():
    clock = SipClock()
    for a in 0.1 * np.arange(50):
        clock.stamp(float(a))
    clock.set_cycle(0.05)
    assert clock.cycle == 0.05 and clock.period == pytest.approx(0.05)
    assert clock.stamp(10.0) == 10.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 0.5), st.booleans(), st.integers(0, 3)), min_size=1, max_size=200),
       st.sampled_from([1.0, 4.0]))
def test_stamps_are_monotonic_and_never_after_arrival(events, scale):
    """Any in-order arrivals: delays, bursts, lost SIPs and reconnects."""
    period = 0.1 / scale
    clock = SipClock(time_scale=scale)
    t, last, k = 50.0, -np.inf, 0
    for delay, reconnect, lost in events:
        if reconnect and k % 7 == 0:
            clock.reset()
        k += 1 + lost
        t = max(t, 50.0 + k * period + delay * period * 10)
        s = clock.stamp(t)
        assert last <= s <= t
        last = s


def test_the_content_of_a_late_sip_tells_a_late_one_from_lost_ones():
    """SIP 300 reaches the host 1.6 cycles late on its own (an emulator starved for CPU); SIPs 450-451 are
    lost. Told from each SIP's motion how many cycles it moves the robot on, the clock stamps the late SIP
    on its own cycle and the one after the gap on its cycle at once (without: both get their arrival)."""
    period = 0.1
    sent, arr = arrivals(700, period, np.random.default_rng(6), jitter=0.01)
    arr[300] = sent[300] + 1.6 * period
    arr = np.maximum.accumulate(arr)
    keep = np.ones(arr.size, bool)
    keep[[450, 451]] = False
    cycles = np.ones(arr.size)
    cycles[452] = 3.0  # the robot moved on three cycles since SIP 449
    clock = SipClock()
    out = np.full(arr.size, np.nan)
    for i in np.flatnonzero(keep):
        out[i] = clock.stamp(float(arr[i]), 0, float(cycles[i]))
    err = np.abs(out - sent)
    assert err[300] < 0.1 * period and err[452] < 0.1 * period
    assert np.nanmax(err[40:]) < 0.1 * period
    assert clock.gaps == 2 and clock.delayed >= 1
