"""Per-beam features of the glass classifiers, computed for whole scans."""

import numpy as np
import pytest

from glassmap.angles import incidence_angles
from glassmap.glass_features import BASELINE_FEATURES, CONTEXT_FEATURES, scan_features
from glassmap.types import LaserGeometry


def _wall_scan(n=181, d=2.0):
    """A straight wall at x = d in front of the laser, beams -45..45 deg."""
    geo = LaserGeometry(n_beams=n, angle_min=-np.pi / 4, angle_increment=np.pi / 2 / (n - 1))
    a = geo.angles
    r = d / np.cos(a)
    inten = 3000.0 * np.cos(a)
    return a, r, inten


def test_baseline_features_are_the_papers_and_a_prefix_of_the_context_ones():
    a, r, i = _wall_scan()
    inc = incidence_angles(a, r)
    xb = scan_features("baseline", a, r, i, inc)
    xc = scan_features("context", a, r, i, inc)
    assert xb.shape == (len(a), len(BASELINE_FEATURES)) and xc.shape == (len(a), len(CONTEXT_FEATURES))
    np.testing.assert_array_equal(xb, xc[:, :3])
    ok = np.isfinite(inc.incidence)
    np.testing.assert_allclose(xb[ok, 0], np.log1p(i[ok]), rtol=1e-6)
    np.testing.assert_allclose(xb[ok, 1], r[ok], rtol=1e-6)
    np.testing.assert_allclose(xb[ok, 2], np.abs(a[ok]), atol=0.01)  # a wall's incidence is the beam angle


def test_context_features_see_echoes_neighbours_and_the_segment():
    a, r, i = _wall_scan()
    n = len(a)
    inc = incidence_angles(a, r)
    i = i.copy()
    i[90] = 12000.0  # a specular peak in the middle of the wall
    echoes = np.full((n, 2), np.nan)
    echoes[85:96, 0] = r[85:96] + 3.0  # a pane: these beams also return from 3 m behind it
    echo_i = np.zeros((n, 2))
    echo_i[85:96, 0] = 500.0
    x = scan_features("context", a, r, i, inc, echoes, echo_i)
    col = {name: k for k, name in enumerate(CONTEXT_FEATURES)}
    assert np.all(x[85:96, col["echo_count"]] == 2) and np.all(x[:85, col["echo_count"]] == 1)
    np.testing.assert_allclose(x[85:96, col["echo_gap_m"]], 3.0, atol=1e-5)
    np.testing.assert_allclose(x[85:96, col["log1p(last_intensity)"]], np.log1p(500.0), rtol=1e-6)
    assert x[89, col["dli_p1"]] > 1.0 and x[91, col["dli_m1"]] > 1.0  # the bright neighbour
    assert x[90, col["dli_max3"]] == 0.0 and x[88, col["dli_max3"]] > 1.0 and x[80, col["dli_max3"]] < 0.2
    assert x[80, col["dli_max10"]] > 1.0
    on = inc.segment >= 0
    assert on.sum() > n // 2
    off = x[on, col["seg_offset"]]
    assert off.min() < 0.05 and np.all((off >= 0) & (off <= 1.0 + 1e-6))
    assert np.all(x[on, col["seg_length_m"]] > np.log1p(2.0))  # one 4 m wall
    assert np.all(x[on, col["seg_dli_max"]] >= 0)
    assert np.isfinite(x).all()


def test_echo_layouts_of_the_simulator_and_the_hokuyo_client_give_the_same_features():
    a, r, i = _wall_scan()
    n = len(a)
    inc = incidence_angles(a, r)
    last = np.full(n, np.nan)
    last[10:20] = r[10:20] + 1.5
    li = np.where(np.isfinite(last), 800.0, 0.0)
    sim = scan_features("context", a, r, i, inc, np.column_stack([r, last]), np.column_stack([i, li]))
    client = scan_features("context", a, r, i, inc, np.column_stack([last, np.full(n, np.nan)]),
                           np.column_stack([li, np.full(n, np.nan)]))
    recorded = scan_features("context", a, r, i, inc, last[:, None], li[:, None])
    np.testing.assert_array_equal(sim, client)
    np.testing.assert_array_equal(sim, recorded)
    single = scan_features("context", a, r, i, inc)
    assert np.all(single[:, 3] == 1) and np.all(single[:, 4:6] == 0)


def test_invalid_readings_give_finite_features():
    a, r, i = _wall_scan()
    r = r.copy()
    i = i.copy()
    r[::7] = np.nan
    r[3::11] = np.inf
    i[5::13] = np.nan
    inc = incidence_angles(a, r)
    x = scan_features("context", a, r, i, inc, np.full((len(a), 2), np.nan), np.full((len(a), 2), np.nan))
    assert np.isfinite(x).all()
    with pytest.raises(ValueError, match="unknown classifier model"):
        scan_features("nonsense", a, r, i, inc)


def test_segment_length_is_numpys_log1p_of_the_end_points_extent_to_the_bit():
    """Column 15 (seg_length_m) is what the numpy code before its kernel (glassmap.features_jit.segment_groups)
    gave: log1p of the hypot of each segment's end points' bounding box (r cos, r sin of the beam angles),
    cast to float32; beams on no segment get 0."""
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world
    from glassmap.train import sample_poses

    world = load_world("office")
    rng = np.random.default_rng(4)
    for pose in sample_poses(world, 6, rng):
        scan = simulate_scan(world, pose, rng).to_scan()
        a, r = scan.angles, scan.ranges
        inc = incidence_angles(a, r)
        x = scan_features("context", a, r, scan.intensities, inc, scan.echoes, scan.echo_intensities)
        ext = np.zeros(inc.n_segments)
        for s in range(inc.n_segments):
            on = inc.segment == s
            px, py = r[on] * np.cos(a)[on], r[on] * np.sin(a)[on]
            ext[s] = np.hypot(px.max() - px.min(), py.max() - py.min())
        want = np.where(inc.segment >= 0, np.log1p(ext)[inc.segment], 0.0).astype(np.float32)
        np.testing.assert_array_equal(x[:, 15], want)


def test_two_echo_share_is_the_windows_float_count_to_the_bit():
    """Column 13 (two_echo_share3) is the share of two-echo beams within +-3 beams (clipped at the scan's
    ends), as the loop that added 1.0 per two-echo beam and divided by the window's length gave."""
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world
    from glassmap.train import sample_poses

    world = load_world("office")
    rng = np.random.default_rng(6)
    for pose in sample_poses(world, 4, rng):
        scan = simulate_scan(world, pose, rng).to_scan()
        inc = incidence_angles(scan.angles, scan.ranges)
        x = scan_features("context", scan.angles, scan.ranges, scan.intensities, inc, scan.echoes,
                          scan.echo_intensities)
        two = x[:, 3] == 2.0
        n = len(two)
        want = np.empty(n, np.float32)
        for b in range(n):
            t = 0.0
            for q in range(max(b - 3, 0), min(b + 4, n)):
                t += 1.0 if two[q] else 0.0
            want[b] = t / float(min(b + 4, n) - max(b - 3, 0))
        assert two.any()
        np.testing.assert_array_equal(x[:, 13], want)
