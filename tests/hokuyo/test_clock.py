"""Sensor clock unwrapping and the sensor -> host time mapping (offset, drift, outliers, jumps)."""

import numpy as np
import pytest

from drivers.clock import ClockMapper, RoundTrip
from drivers.hokuyo.clock import TimestampUnwrapper

WRAP = 1 << 24  # ms: 16777.216 s


def test_unwrap_across_the_24_bit_wrap_and_small_steps_back():
    u = TimestampUnwrapper()
    assert u.unwrap(WRAP - 50) == WRAP - 50
    assert u.unwrap(WRAP - 25) == WRAP - 25
    assert u.unwrap(0) == WRAP  # wrapped
    assert u.unwrap(25) == WRAP + 25
    assert u.unwrap(10) == WRAP + 10  # a small step back stays a step back
    assert u.unwrap(WRAP // 2 + 5) == WRAP + WRAP // 2 + 5  # forward by less than half the range
    u.reset()
    assert u.unwrap(7) == 7


def stream(mapper, n, *, offset=1000.0, slope=1.0, latency=0.02, period=0.025, s0=5.0, jitter_seed=0,
           late=(), jump_at=None, jump=0.0, odd=()):
    """Feed n scans; returns (true host times, mapped host times)."""
    rng = np.random.default_rng(jitter_seed)
    true, got = [], []
    for k in range(n):
        s = s0 + k * period
        t = offset + slope * s
        arrival = t + latency + rng.exponential(0.001) + (0.2 if k in late else 0.0)
        stamp = s + (jump if jump_at is not None and k >= jump_at else 0.0) + (30.0 if k in odd else 0.0)
        true.append(t)
        got.append(mapper.observe(stamp, arrival))
    return np.array(true), np.array(got)


def test_tm1_offset_plus_streaming_gives_sub_millisecond_host_times_with_drift():
    m = ClockMapper()
    # TM1 samples: the one with the smallest round trip wins (its midpoint is host(s)).
    m.add_round_trips([RoundTrip(1004.0, 1004.030, 4.010), RoundTrip(1004.9995, 1005.0005, 5.0),
                       RoundTrip(1006.0, 1006.01, 6.003)])
    assert m.anchor.sensor == 5.0
    true, got = stream(m, 2000, slope=1 + 50e-6)  # 50 ppm drift
    err = np.abs(got - true)[100:]
    assert err.max() < 1e-3
    assert m.slope == pytest.approx(1 + 50e-6, abs=5e-6)
    assert m.latency == pytest.approx(0.02, abs=1e-3)


def test_late_scans_do_not_move_the_clock():
    m = ClockMapper()
    m.add_round_trips([RoundTrip(1004.9995, 1005.0005, 5.0)])
    true, got = stream(m, 600, late=set(range(200, 600, 7)))
    assert np.abs(got - true)[100:].max() < 1e-3
    assert m.jumps == 0


@pytest.mark.parametrize("stalled_block", [1, 2, 3])
def test_a_host_stall_while_the_rate_is_being_learnt_is_not_a_clock_jump(stalled_block):
    """An emulator at 4x real time (0.25 host s per sensor s, far from the initial guess of 1) and a
    0.3 s host stall over a whole block of 8 scans while the rate is fitted: no jump, the rate is learnt."""
    m = ClockMapper()
    late = set(range(8 * stalled_block, 8 * stalled_block + 8))
    for k in range(200):
        s = 5.0 + 0.025 * k
        m.observe(s, 1000.0 + 0.25 * s + 0.002 + (0.3 if k in late else 0.0))
    assert m.jumps == 0
    assert m.slope == pytest.approx(0.25, abs=1e-6)


def test_a_confirmed_clock_jump_reanchors_without_a_host_time_jump():
    m = ClockMapper()
    m.add_round_trips([RoundTrip(1004.9995, 1005.0005, 5.0)])
    true, got = stream(m, 800, jump_at=400, jump=-120.0)
    assert m.jumps == 1
    err = np.abs(got - true)
    assert err[100:400].max() < 1e-3
    assert err[400:].max() < 5e-3  # the jump's own scans use arrival time - latency
    assert np.all(np.diff(got[100:]) > 0)


def test_a_single_odd_stamp_is_an_outlier_not_a_jump():
    m = ClockMapper()
    m.add_round_trips([RoundTrip(1004.9995, 1005.0005, 5.0)])
    true, got = stream(m, 600, odd={300})
    assert m.jumps == 0 and m.outliers == 1
    assert np.abs(got - true)[100:].max() < 5e-3


def test_without_tm1_the_latency_defaults_to_one_scan_time():
    m = ClockMapper(default_latency=0.025)
    true, got = stream(m, 400, latency=0.025)
    assert np.abs(got - true)[50:].max() < 2e-3


def test_bad_arguments():
    with pytest.raises(ValueError):
        ClockMapper(block=0)


def _best_line(s, a, i, j, s0, a0):
    """The numpy fit over the candidate pairs (i, j) of points (s, a) relative to (s0, a0): the references'
    core (numpy's argmin of no pairs raises ValueError)."""
    ds = s[j] - s[i]
    ok = ds > 0
    i, j, ds = i[ok], j[ok], ds[ok]
    b = (a[j] - a[i]) / ds
    c = a[i] - b * s[i]
    resid = a[None, :] - (c[:, None] + b[:, None] * s[None, :])
    feasible = (resid.min(axis=1) >= -1e-9) & (b > 0)
    cost = np.where(feasible, resid.sum(axis=1), np.inf)
    k = int(np.argmin(cost))
    if not np.isfinite(cost[k]):
        return None
    return float(a0 + c[k] - b[k] * s0), float(b[k])


def _lower_envelope_all_pairs(s, a):
    """The envelope fit before it tried only the points near the lower hull: every pair (reference)."""
    i, j = np.triu_indices(s.size, 1)
    return _best_line(s - s[0], a - a[0], i, j, s[0], a[0])


def test_the_envelope_fit_equals_the_all_pairs_fit():
    from drivers.clock import _lower_envelope

    rng = np.random.default_rng(7)
    cases = []
    for n in (4, 5, 9, 40):
        for _ in range(150):
            s = np.sort(rng.uniform(0, 8, n)) + 1.7e9 * rng.integers(0, 2)
            jitter = rng.exponential(1e-3, n) * (rng.random(n) < 0.7)  # many points exactly on the line
            a = 1.7e9 + 0.3 + (1 + rng.normal(0, 1e-4)) * (s - s[0]) + jitter
            cases.append((s, a))
    for n in (4, 40):  # duplicated sensor times, collinear runs, lines below by less than 1e-9, falling lines
        s = np.repeat(np.arange(n // 2, dtype=float) * 0.2, 2)
        cases.append((s, 1.0 + s + np.tile([0.0, 1e-3], n // 2)))
        s = np.arange(n) * 0.2
        cases.append((s, 2.0 + 0.5 * s + (rng.random(n) < 0.5) * 5e-10))
        cases.append((s, 2.0 - 0.5 * s + rng.exponential(1e-3, n)))
        sh = rng.permutation(s)  # out of order
        cases.append((sh, 2.0 + sh + rng.exponential(1e-3, n)))
    for s, a in cases:
        assert _lower_envelope(s, a) == _lower_envelope_all_pairs(s, a)


def _near_lower_hull_numpy(s, a, tol):
    """The hull selection before the compiled fit (lexsort, monotone chain, np.interp): the reference."""
    order = np.lexsort((a, s))
    so, ao = s[order], a[order]
    first = np.ones(so.size, dtype=bool)
    first[1:] = so[1:] != so[:-1]
    hx, hy = [], []
    for x, y in zip(so[first].tolist(), ao[first].tolist()):
        while len(hx) >= 2 and (hx[-1] - hx[-2]) * (y - hy[-2]) - (hy[-1] - hy[-2]) * (x - hx[-2]) <= 0:
            hx.pop()
            hy.pop()
        hx.append(x)
        hy.append(y)
    return np.flatnonzero(a - np.interp(s, hx, hy) <= tol)


def test_the_compiled_hull_and_sum_equal_numpy_to_the_bit():
    """Sorted, shuffled and duplicated sensor times, epoch offsets, points on and near the hull; sums of 1 to
    300 values (numpy's pairwise order)."""
    from drivers.clock_jit import _sum, near_lower_hull

    rng = np.random.default_rng(8)
    for _ in range(3000):
        n = int(rng.integers(1, 50))
        s = np.sort(rng.uniform(0, 8, n))
        if rng.random() < 0.3:
            s = np.round(s, 1)  # equal sensor times
        if rng.random() < 0.3:
            s = rng.permutation(s)
        a = 0.3 + (1 + rng.normal(0, 1e-4)) * s + rng.exponential(1e-3, n) * (rng.random(n) < 0.7)
        tol = float(rng.choice([1e-6, 0.0, 1e-3]))
        np.testing.assert_array_equal(near_lower_hull(s, a, tol), _near_lower_hull_numpy(s, a, tol))
    for n in range(1, 300):
        x = rng.normal(0, 1, n) * 10.0 ** rng.uniform(-9, 3, n)
        assert _sum(x) == x.sum()


def _lower_envelope_numpy(s, a):
    """The envelope fit before it was compiled (pairs of points near the hull, in numpy): the reference."""
    s0, a0 = s[0], a[0]
    s, a = s - s0, a - a0
    near = _near_lower_hull_numpy(s, a, 1e-6)
    i, j = np.triu_indices(near.size, 1)
    return _best_line(s, a, near[i], near[j], s0, a0)


def test_the_compiled_fit_equals_the_numpy_fit_to_the_bit():
    """Shuffled, duplicated and rounded sensor times (also no two near the hull in increasing order: a
    ValueError), epoch offsets, rising, falling and steep lines."""
    from drivers.clock import _lower_envelope

    rng = np.random.default_rng(9)
    outcomes = set()
    for _ in range(3000):
        n = int(rng.integers(4, 60))
        s = np.sort(rng.uniform(0, 8, n))
        if rng.random() < 0.5:
            s = np.round(s, int(rng.integers(1, 4)))
        if rng.random() < 0.3:
            s = rng.permutation(s)
        s = s + 1.7e9 * rng.integers(0, 2)
        slope = 1 + rng.normal(0, 1e-4) if rng.random() < 0.7 else rng.normal(0, 2)
        a = 1.7e9 * rng.integers(0, 2) + slope * (s - s[0]) + rng.exponential(1e-3, n) * (rng.random(n) < 0.7)
        got, want = [], []
        for f, out in ((_lower_envelope, got), (_lower_envelope_numpy, want)):
            try:
                out.append(f(s, a))
            except ValueError:  # the numpy code's argmin of no pairs: now no line
                out.append(None)
        assert got == want
        outcomes.add(type(want[0]))
    assert outcomes == {tuple, type(None)}  # lines, no line


def test_a_frozen_sensor_stamp_leaves_the_stamps_on_the_arrivals():
    """No two blocks at different sensor times: no line to fit (the numpy fit raised ValueError from the
    scan's receive path); the stamps stay arrival - latency."""
    from drivers.clock import _lower_envelope

    assert _lower_envelope(np.full(5, 3.0), 1.0 + np.arange(5.0)) is None
    m = ClockMapper(default_latency=0.025)
    arrivals = 100.0 + 0.025 * np.arange(400)
    stamps = [m.observe(7.0, t) for t in arrivals]
    assert not m.fitted
    assert np.allclose(stamps, arrivals - 0.025)
