"""The driver's odometry covariance is consistent with the emulator's robot, driving straight and turning in
place, over 100 seeds (issue: 3-4x too wide straight, NEES 10.7 turning with the track width unmodelled)."""

import dataclasses

import pytest

from drivers.pioneer.odometry import CovarianceModel
from drivers.pioneer.odometry_eval import evaluate

SEEDS = list(range(100))


@pytest.mark.parametrize("motion", ["straight", "turn"])
def test_nees_in_band_against_the_emulators_robot(motion):
    r = evaluate(motion, "emulator", SEEDS)
    assert 1.5 <= r.nees_mean <= 6.0 and r.inside_95 >= 0.85, r


@pytest.mark.parametrize("motion", ["straight", "turn"])
def test_nees_follows_chi_square_for_robots_drawn_from_the_model(motion):
    """Robots whose systematic errors are drawn from the model's prior: mean NEES of 100 runs of a consistent
    3-dof model lies in [2.5, 3.5] about 95 % of the time (chi-square(300) / 100)."""
    r = evaluate(motion, "drawn", SEEDS)
    assert 2.3 <= r.nees_mean <= 3.8 and r.inside_95 >= 0.88, r


def test_without_the_track_width_term_turning_is_overconfident():
    r = evaluate("turn", "emulator", SEEDS[:40], dataclasses.replace(CovarianceModel(), track_sigma=0.0))
    assert r.nees_mean > 6.0
