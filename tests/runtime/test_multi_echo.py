"""Multi-echo scans in the runtime: streamed when the classifier reads echoes, the last echo recorded and read
back (so a replay sees what the live run saw), single-echo input falling back to the baseline model."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from runtime import messages as M
from runtime.config import ConfigError, RuntimeConfig
from runtime.readers import iter_messages
from runtime.recorder import McapRecorder
from runtime.sink import RecordingSink
from tests.runtime.factories import make_scan


def _multi_echo(scan):
    """The Hokuyo client's layout: echoes (n, 2) = second and third echo, NaN where absent."""
    n = scan.ranges.shape[0]
    e = np.full((n, 2), np.nan)
    ei = np.full((n, 2), np.nan)
    e[100:200, 0] = scan.ranges[100:200] + 2.0
    ei[100:200, 0] = 700.0
    e[150:160, 1] = scan.ranges[150:160] + 4.0  # a third echo: the last one counts
    ei[150:160, 1] = 300.0
    scan.echoes, scan.echo_intensities = e, ei
    return scan


def test_last_echo_is_recorded_and_read_back(tmp_path):
    tb = M.TimeBase(offset_ns=1_700_000_000_000_000_000)
    live = [M.as_recorded_scan(_multi_echo(make_scan(1.0 + 0.025 * k, seq=k)), tb) for k in range(3)]
    live.append(M.as_recorded_scan(make_scan(1.2, seq=9), tb))  # a single-echo scan in between
    path = tmp_path / "me.mcap"
    with McapRecorder(path) as rec:
        sink = RecordingSink(rec, tb)
        for s in live:
            sink.scan(s)
    assert rec.stats.written["/scan/last_echo"] == 3
    replay = [m for m in iter_messages(path)]
    assert len(replay) == 4
    s0 = live[0]
    assert s0.echoes.shape == (1081, 1)
    np.testing.assert_allclose(s0.echoes[150:160, 0], s0.ranges[150:160] + 4.0, atol=1e-5)
    np.testing.assert_allclose(s0.echoes[100:150, 0], s0.ranges[100:150] + 2.0, atol=1e-5)
    assert np.isnan(s0.echoes[:100, 0]).all()
    for a, b in zip(live[:3], replay[:3]):
        np.testing.assert_array_equal(a.echoes, b.echoes)
        np.testing.assert_array_equal(a.echo_intensities, b.echo_intensities)
        np.testing.assert_array_equal(a.ranges, b.ranges)
    assert replay[3].echoes is None


def test_multi_echo_setting_and_the_processor_wants_echoes():
    from runtime.processor import MappingProcessor

    cfg = RuntimeConfig()
    assert cfg.laser.multi_echo == "auto"
    cfg.laser.multi_echo = "sometimes"
    with pytest.raises(ConfigError, match="multi_echo"):
        cfg.validate()
    assert MappingProcessor(RuntimeConfig().mapping).wants_echoes  # the shipped context model reads echoes


def test_single_echo_scans_fall_back_to_the_baseline_with_one_log_line(caplog):
    from glassmap.classifier import GlassClassifier
    from glassmap.mapping import GlassMapper
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world

    world = load_world("office")
    rng = np.random.default_rng(3)
    sims = [simulate_scan(world, np.array([3.0 + k, 1.2, 0.3 * k]), rng) for k in range(3)]
    mapper = GlassMapper(classifier=GlassClassifier.load_default())
    base = GlassMapper(classifier=GlassClassifier.load_default("baseline"))
    with caplog.at_level(logging.WARNING, logger="glassmap.mapping"):
        for sim in sims:
            scan = sim.to_scan()
            scan.echoes = scan.echo_intensities = None
            got, use = mapper.classify(scan)
            want, _ = base.classify(scan)
            np.testing.assert_allclose(got.p_glass[use], want.p_glass[use])
        multi, use = mapper.classify(sims[0].to_scan())  # with echoes: the context model again
    lines = [r for r in caplog.records if "single-echo" in r.getMessage()]
    assert len(lines) == 1 and "baseline" in lines[0].getMessage()
    assert mapper.classifier_for(sims[0].to_scan()) is mapper.classifier


def _numpy_last_echo(scan):
    """``runtime.messages.last_echo`` before its compiled loop (issue 19e)."""
    r = scan.ranges
    e = np.asarray(scan.echoes, dtype=np.float64).reshape(r.shape[0], -1)
    ei = (np.zeros_like(e) if scan.echo_intensities is None
          else np.asarray(scan.echo_intensities, dtype=np.float64).reshape(r.shape[0], -1))
    with np.errstate(invalid="ignore"):
        fin = np.isfinite(e) & np.isfinite(r)[:, None] & (np.abs(e - r[:, None]) > 1e-6)
    has = fin.any(axis=1)
    col = e.shape[1] - 1 - np.argmax(fin[:, ::-1], axis=1)
    rows = np.arange(r.shape[0])
    return np.where(has, e[rows, col], np.nan), np.where(has, np.nan_to_num(ei[rows, col], nan=0.0), 0.0)


def test_last_echo_equals_the_numpy_selection_to_the_bit():
    """Echoes equal to the first one, NaN / inf ranges and intensities, one to three columns, no intensities."""
    rng = np.random.default_rng(2)
    for k in (1, 2, 3):
        scan = make_scan(0.0)
        n = scan.ranges.shape[0]
        scan.ranges[rng.random(n) < 0.05] = np.nan
        scan.ranges[rng.random(n) < 0.05] = np.inf
        e = scan.ranges[:, None] + rng.uniform(0.0, 3.0, (n, k))
        e[rng.random((n, k)) < 0.3] = np.nan
        e[rng.random((n, k)) < 0.05] = np.inf
        same = rng.random((n, k)) < 0.1  # an echo at the first one's range is not a further echo
        e[same] = np.broadcast_to(scan.ranges[:, None], (n, k))[same]
        ei = rng.uniform(0, 5000, (n, k))
        ei[rng.random((n, k)) < 0.1] = np.nan
        ei[rng.random((n, k)) < 0.05] = np.inf
        ei[rng.random((n, k)) < 0.05] = -np.inf
        for scan.echoes, scan.echo_intensities in ((e, ei), (e[:, ::-1], None)):
            got, want = M.last_echo(scan), _numpy_last_echo(scan)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def _numpy_as_recorded(scan):
    """as_recorded_scan's arrays as numpy computed them before the compiled kernel."""
    last = M.last_echo(scan)
    with np.errstate(over="ignore"):  # intensities beyond float32's range become inf
        return tuple(x.astype(np.float32).astype(np.float64) for x in (scan.ranges, last[0][:, None],
                                                                         last[1][:, None]))


def test_as_recorded_scan_equals_the_numpy_rounding_to_the_bit():
    """Ranges and last echoes through float32, with NaN / +-inf values, intensities beyond float32's range,
    no echo intensities, float32 input."""
    rng = np.random.default_rng(3)
    tb = M.TimeBase(offset_ns=1_700_000_000_000_000_000)
    for k in (1, 2, 3):
        scan = make_scan(1.0)
        n = scan.ranges.shape[0]
        scan.ranges = scan.ranges + rng.uniform(-1e-3, 1e-3, n)
        scan.ranges[rng.random(n) < 0.05] = np.nan
        scan.ranges[rng.random(n) < 0.05] = np.inf
        e = scan.ranges[:, None] + rng.uniform(0.0, 3.0, (n, k))
        e[rng.random((n, k)) < 0.3] = np.nan
        e[rng.random((n, k)) < 0.05] = -np.inf
        ei = rng.uniform(0, 5000, (n, k))
        ei[rng.random((n, k)) < 0.1] = np.nan
        ei[rng.random((n, k)) < 0.05] = np.inf
        ei[rng.random((n, k)) < 0.05] = 1e300
        for scan.echoes, scan.echo_intensities in ((e, ei), (e[:, ::-1], None), (e.astype(np.float32), ei)):
            got = M.as_recorded_scan(scan, tb)
            want = _numpy_as_recorded(scan)
            for a, b in zip((got.ranges, got.echoes, got.echo_intensities), want):
                assert a.dtype == b.dtype and a.shape == b.shape
                np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))
