"""The shipped classifier weights load without network and separate simulated glass from wall beams."""

import math

import numpy as np
import pytest

from glassmap.angles import incidence_angles
from glassmap.classifier import ClassifierError, GlassClassifier
from glassmap.eval.metrics import binary_report


@pytest.fixture(scope="module")
def clf():
    return GlassClassifier.load_default()


def test_shipped_weights_are_small_and_load(clf):
    from glassmap.classifier import MODEL_DIR

    assert (MODEL_DIR / "glass_mlp.pt").stat().st_size < 200_000
    assert len([m for m in clf.model if m.__class__.__name__ == "Linear"]) == 4
    assert clf.meta.temperature > 0


def test_known_beams(clf):
    # a saturated return at normal incidence at 2 m: the specular glass peak
    p = clf.predict(np.array([12000.0, 800.0]), np.array([2.0, 2.0]), np.array([0.0, math.radians(40)]))
    assert p[0] > 0.5 > p[1]
    assert p.shape == (2,) and np.all((p > 0) & (p < 1))


@pytest.mark.parametrize("world_name", ["office", "lobby"])  # a training world and the held-out one
def test_classifies_simulated_glass_and_wall_beams(clf, world_name):
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world
    from glassmap.train import sample_poses

    world = load_world(world_name)
    rng = np.random.default_rng(7)
    ys, ps = [], []
    for pose in sample_poses(world, 25, rng):
        s = simulate_scan(world, pose, rng)
        inc = incidence_angles(s.geometry.angles, s.ranges).incidence
        use = np.isfinite(inc) & np.isfinite(s.ranges)
        ps.append(clf.predict(s.intensities[use], s.ranges[use], inc[use]))
        ys.append(s.is_glass[use])
    y, p = np.concatenate(ys), np.concatenate(ps)
    assert y.sum() > 20
    rep = binary_report(y, p)
    assert rep.roc_auc > 0.9
    assert rep.balanced_accuracy > 0.8
    assert np.mean(p[y]) > 0.6 and np.mean(p[~y]) < 0.2


def test_bad_inputs(clf, tmp_path):
    with pytest.raises(ValueError):
        clf.predict(np.ones(3), np.ones(2), np.ones(3))
    with pytest.raises(ValueError, match="finite"):
        clf.predict(np.array([np.nan]), np.array([1.0]), np.array([0.1]))
    assert clf.predict(np.zeros(0), np.zeros(0), np.zeros(0)).shape == (0,)
    with pytest.raises(ClassifierError, match="glassmap glass train"):
        GlassClassifier.load(tmp_path / "missing")
