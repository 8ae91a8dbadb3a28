"""Regression checks of the README's headline figures, recomputed from the code (never read from a file):
the pose estimator's accuracy and covariance consistency, the ordering of the paper's experiment, and the
shipped classifier's metrics on the held-out world. Slow: ``scripts/dev.sh slow``.

Thresholds are the README's figures with a margin for the run-to-run spread of the simulator seeds; a
failure means a change made a headline figure worse, not that the machine was busy (no timing here)."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


@pytest.mark.parametrize("world", ["office", "lobby"])  # a tuning world and the held-out one
def test_pose_estimator_is_accurate_and_consistent(world):
    from glassmap.pose.evaluate import evaluate_run

    m = evaluate_run(world, None, seed=0)
    assert m.ate_rmse < 0.05  # the target; README: office 1.1 cm, lobby 0.5 cm
    assert m.odom_ate_rmse > 3 * m.ate_rmse  # matching does the work, not the odometry
    assert 1.5 <= m.nees_mean <= 6.0  # README: office 2.02, lobby 3.01 (ideal 3)
    assert m.inside_95 >= 0.85


def test_paper_experiment_robust_registration_beats_direct():
    from glassmap.eval.experiment import rows_of, run_trials, summarise
    from glassmap.eval.trial import TrialConfig

    cfg = TrialConfig(methods=("direct", "robust3", "robust5"), scan_rate=5.0)
    summary = summarise(rows_of(run_trials(cfg, list(range(1000, 1010)), progress=False)))
    d, r3, r5 = summary["direct"], summary["robust3"], summary["robust5"]
    # README (50 trials): mean 0.135 / 0.072 / 0.078, worst 0.223 / 0.086 / 0.092, std 0.035 / 0.006 / 0.006
    for r in (r3, r5):
        assert r["mean"] < 0.75 * d["mean"]
        assert r["worst"] < d["worst"] and r["std"] < d["std"]


def test_shipped_classifier_on_the_held_out_world():
    from glassmap.classifier import GlassClassifier
    from glassmap.eval.metrics import binary_report
    from glassmap.sim.world import load_world
    from glassmap.train import heldout_laser_params, sample_poses, simulate_beams

    clf = GlassClassifier.load_default()
    world = load_world("lobby")
    rng = np.random.default_rng(12345)
    held = simulate_beams(world, sample_poses(world, 300, rng), heldout_laser_params(), rng)
    rep = binary_report(held.y, clf.predict(np.expm1(held.x[:, 0]), held.x[:, 1], held.x[:, 2]))
    # README: balanced accuracy 0.945, precision 0.684, recall 0.903, ROC-AUC 0.986, calibration error 0.030
    assert rep.n_glass > 500
    assert rep.balanced_accuracy >= 0.92 and rep.recall >= 0.85 and rep.precision >= 0.6
    assert rep.roc_auc >= 0.97 and rep.ece <= 0.05
