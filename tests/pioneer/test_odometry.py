"""Odometry from SIPs: 15-bit unwrapping in both directions, heading wrap, factors, covariance growth."""

import math

import numpy as np
import pytest

from drivers.pioneer.errors import UnsupportedRobotError
from drivers.pioneer.odometry import MODELS, CovarianceModel, OdometryTracker, model_for
from drivers.pioneer.sip import StandardSIP


def sip(x, y=0, th=0, lvel=0, rvel=0, bits=15):
    mask = (1 << bits) - 1
    return StandardSIP(False, x & mask, y & mask, th, lvel, rvel, 120)


def track(raw_x, model="p3dx-sh", bits=15, th=None):
    tr = OdometryTracker(MODELS[model])
    out = []
    for k, x in enumerate(raw_x):
        out.append(tr.update(sip(x, th=0 if th is None else th[k], bits=bits), float(k)))
    return out


@pytest.mark.parametrize("bits", [15, 16])
def test_forward_across_the_wrap(bits):
    # controller x in units: 32000 .. 33500 crosses 0x8000 (15-bit) and, for bits=16, is masked the same way
    raw = list(range(32000, 33600, 100))
    odo = track(raw, bits=bits)
    steps = np.diff([o.x for o in odo])
    assert np.allclose(steps, 0.1)  # 100 units x 1 mm, never a jump of -32.768 m
    assert odo[-1].x - odo[0].x == pytest.approx(1.5)


@pytest.mark.parametrize("bits", [15, 16])
def test_backward_across_the_wrap(bits):
    raw = list(range(300, -1300, -100))  # 0.3 m down to -1.2 m: wraps below zero
    odo = track(raw, bits=bits)
    assert odo[0].x == pytest.approx(0.3)
    assert odo[-1].x == pytest.approx(-1.2)
    assert np.allclose(np.diff([o.x for o in odo]), -0.1)


def test_large_steps_are_followed_not_discarded():
    # 1.5 m per SIP (15 m/s) on a p3dx-sh is a legitimate-looking step for the unwrapper
    odo = track([0, 1500, 3000, 4500, 6000])
    assert [round(o.x, 3) for o in odo] == [0.0, 1.5, 3.0, 4.5, 6.0]


def test_p3dx_distance_factor():
    odo = track([0, 1000, 2000], model="p3dx")
    assert odo[-1].x == pytest.approx(2000 * 0.485 / 1000)


def test_first_sip_anchors_signed_15_bit():
    (o,) = track([(-412) & 0x7FFF], model="p3dx")
    assert o.x == pytest.approx(-412 * 0.485e-3)


def test_heading_wraps_at_4096_units_both_ways():
    th = [2000, 2040, -2040, -2000, -2040, 2040, 2000]
    odo = track([0] * len(th), th=th)
    yaws = [o.yaw for o in odo]
    assert yaws[0] == pytest.approx(2000 * 0.001534)
    assert all(-math.pi < y <= math.pi for y in yaws)
    # unwrapped steps: +40, +16 (through +-2048), +40, -40, -16, -40 units
    tr = OdometryTracker(MODELS["p3dx-sh"])
    for k, t in enumerate(th):
        tr.update(sip(0, th=t), k)
    assert tr.yaw_unwrapped == pytest.approx(2000 * 0.001534)
    assert tr.rotation == pytest.approx((40 + 16 + 40 + 40 + 16 + 40) * 0.001534)


def test_velocities_from_wheel_speeds():
    tr = OdometryTracker(MODELS["p3dx-sh"])
    o = tr.update(sip(0, lvel=100, rvel=300), 0.0)
    assert o.v == pytest.approx(0.2)
    assert o.omega == pytest.approx((300 - 100) / 2 * 0.0056)


def test_covariance_grows_with_distance_and_turn_not_when_still():
    tr = OdometryTracker(MODELS["p3dx-sh"], CovarianceModel())
    assert np.all(tr.update(sip(0), 0).covariance == 0)
    still = tr.update(sip(0), 1).covariance
    assert np.all(still == 0)
    c1 = tr.update(sip(1000), 2).covariance  # 1 m straight along x: 1 m on each wheel
    n, t = CovarianceModel(), tr.track
    assert t == pytest.approx(0.357, abs=1e-3)  # 2 / diff_conv
    # distance error (nL + nR + eps_L + eps_R) / 2; rotation error (nR - nL + eps_R - eps_L) / T
    assert c1[0, 0] == pytest.approx((n.slip ** 2 * 2 + n.scale_sigma ** 2 * 2) / 4)
    assert c1[2, 2] == pytest.approx((n.slip ** 2 * 2 + n.scale_sigma ** 2 * 2) / t ** 2)
    assert c1[1, 1] > 0  # the heading error spreads into y
    c2 = tr.update(sip(2000), 3).covariance
    assert c2[0, 0] > c1[0, 0] and c2[1, 1] > c1[1, 1] and c2[2, 2] > c1[2, 2]
    for c in (c1, c2):
        assert np.allclose(c, c.T) and np.all(np.linalg.eigvalsh(c) >= -1e-12)


def test_turning_in_place_heading_variance_has_the_track_width_term():
    """A quarter turn in place: each wheel travels a T / 2; var_yaw = slip^2 a / T (random) + scale_sigma^2
    a^2 / 2 (wheel scales) + track_sigma^2 a^2 (track width). Two turns: the systematic part grows with
    the square of the angle (the same track error every time), the random part linearly."""
    n = CovarianceModel()
    tr = OdometryTracker(MODELS["p3dx-sh"], n)
    tr.update(sip(0), 0.0)
    a = 1024 * 0.001534
    v1 = tr.update(sip(0, th=1024), 1.0).covariance[2, 2]
    assert v1 == pytest.approx(n.slip ** 2 * a / tr.track + n.scale_sigma ** 2 * a ** 2 / 2 + n.track_sigma ** 2 * a ** 2)
    v2 = tr.update(sip(0, th=2048 - 4096), 2.0).covariance[2, 2]
    a2 = 2 * a
    assert v2 == pytest.approx(n.slip ** 2 * a2 / tr.track + n.scale_sigma ** 2 * a2 ** 2 / 2 + n.track_sigma ** 2 * a2 ** 2)


def test_an_impossible_step_is_rejected_and_the_pose_stays_continuous(caplog):
    """A SIP whose position passed the checksum but jumped 31.7 m in 0.1 s (a robot at rest) is not
    integrated; the next good SIP continues from the last good pose."""
    tr = OdometryTracker(MODELS["p3dx-sh"])
    good = [tr.update(sip(500), 0.0), tr.update(sip(500), 0.1)]
    bad = tr.update(sip(500 - 31700), 0.2)
    after = tr.update(sip(510), 0.3)
    assert bad.x == good[-1].x == pytest.approx(0.5)
    assert after.x == pytest.approx(0.51)
    assert tr.rejected_steps == 1 and tr.reanchors == 0
    assert "implausible step" in caplog.text
    assert np.all(np.isfinite(after.covariance)) and after.covariance[1, 1] < 1e-4


def test_a_controller_jump_that_stays_is_reanchored():
    """Three SIPs that agree with each other at a new position (a controller reset) re-anchor the tracker:
    the odometry pose does not jump, and follows the controller's motion from there."""
    tr = OdometryTracker(MODELS["p3dx-sh"])
    tr.update(sip(5000), 0.0)
    tr.update(sip(5000), 0.1)
    out = [tr.update(sip(x), 0.2 + 0.1 * k) for k, x in enumerate([0, 0, 0, 100])]
    assert tr.rejected_steps == 3 and tr.reanchors == 1
    assert [round(o.x, 3) for o in out] == [5.0, 5.0, 5.0, 5.1]


def test_unknown_subclass_names_the_fix():
    assert model_for("P3DX-SH").dist_conv == 1.0
    with pytest.raises(UnsupportedRobotError, match="model='p3dx'"):
        model_for("p3at")


def test_a_sips_content_tells_how_many_cycles_it_moves_the_robot_on():
    """0.4 m/s straight (40 mm per 0.1 s cycle), then turning in place at 1.12 rad/s (73 units per cycle): one
    cycle, two (a SIP lost between), or too slow to tell."""
    tr = OdometryTracker(MODELS["p3dx-sh"])
    assert tr.cycles_since_last(sip(0, lvel=400, rvel=400), 0.1) is None  # nothing to compare with yet
    tr.update(sip(0, lvel=400, rvel=400), 0.0)
    assert tr.cycles_since_last(sip(40, lvel=400, rvel=400), 0.1) == pytest.approx(1.0)
    assert tr.cycles_since_last(sip(80, lvel=400, rvel=400), 0.1) == pytest.approx(2.0)
    tr.update(sip(40, th=0, lvel=-200, rvel=200), 0.1)  # wheel speeds +-200 mm/s: 1.12 rad/s
    assert tr.cycles_since_last(sip(40, th=73, lvel=-200, rvel=200), 0.1) == pytest.approx(1.0, abs=0.01)
    assert tr.cycles_since_last(sip(40, th=146, lvel=-200, rvel=200), 0.1) == pytest.approx(2.0, abs=0.02)
    tr.update(sip(40, th=146, lvel=0, rvel=0), 0.3)
    assert tr.cycles_since_last(sip(41, th=146, lvel=5, rvel=5), 0.1) is None  # creeping: too slow to tell
    # from rest to 0.4 m/s in one cycle: a SIP's wheel speeds are the encoders' over the cycle it reports
    assert tr.cycles_since_last(sip(80, th=146, lvel=400, rvel=400), 0.1) == pytest.approx(1.0)
