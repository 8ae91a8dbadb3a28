"""glassmap.beam_trig: the cosines, sines and median step of the beam angles, kept for the last angle array:
the numbers numpy gives for any subset of the beams, and new numbers as soon as the angles change."""

import numpy as np

from glassmap.beam_trig import beam_trig, median_step
from glassmap.types import LaserGeometry


def test_values_are_numpys_for_any_subset_of_the_beams():
    a = LaserGeometry().angles
    t = beam_trig(a)
    assert beam_trig(a.copy()) is t  # the same values: kept
    rng = np.random.default_rng(2)
    for _ in range(50):
        idx = np.flatnonzero(rng.random(a.size) < rng.random())
        order = rng.permutation(a.size)[: rng.integers(1, a.size)]
        for sel in (idx, order):
            np.testing.assert_array_equal(t.cos[sel], np.cos(a[sel]))
            np.testing.assert_array_equal(t.sin[sel], np.sin(a[sel]))
    assert t.median_step == float(np.median(np.diff(a)))
    assert not t.cos.flags.writeable and not t.angles.flags.writeable


def test_other_angles_get_their_own_values():
    a = LaserGeometry().angles
    t = beam_trig(a)
    b = a.copy()
    b[500] += 1e-12  # one beam differs by a hair
    u = beam_trig(b)
    assert u is not t and u.cos[500] == np.cos(b[500])
    c = LaserGeometry(n_beams=721, angle_increment=np.pi / 480).angles
    v = beam_trig(c)
    np.testing.assert_array_equal(v.sin, np.sin(c))
    assert v.median_step == float(np.median(np.diff(c)))
    b[3] = np.nan  # NaN never equals itself: computed again, never mixed up
    assert beam_trig(b) is not beam_trig(b)
    m = a.copy()
    t = beam_trig(m)
    m[0] = 5.0  # the caller's array changes after the call: the kept copy does not
    assert beam_trig(a).cos is t.cos and t.angles[0] == a[0] and t.cos[0] == np.cos(a[0])  # kept


def test_a_lasers_angles_are_one_read_only_array_that_is_not_compared_again(monkeypatch):
    a = LaserGeometry().angles
    assert a is LaserGeometry().angles and not a.flags.writeable  # the same array for every scan
    assert LaserGeometry(n_beams=721).angles is not a
    t = beam_trig(a)

    def no_compare(*args):
        raise AssertionError("values compared")

    monkeypatch.setattr(np, "array_equal", no_compare)
    assert beam_trig(a) is t


def test_median_step_of_uneven_and_short_arrays():
    assert median_step(np.array([0.0])) == 0.0
    assert median_step(np.array([0.0, 0.1, 0.3, 0.35])) == np.median([0.1, 0.2, 0.05])
    assert median_step(np.array([0.0, 0.1, 0.3, 0.35, 0.5])) == np.median([0.1, 0.2, 0.05, 0.15])
