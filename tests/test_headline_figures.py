"""Regression checks of the README's headline figures, recomputed from the code (never read from a file):
the pose estimator's accuracy and covariance consistency, the ordering of the paper's experiment, and the
shipped classifiers' metrics on test worlds. Slow: ``scripts/dev.sh slow``.

Thresholds are the README's figures with a margin for the run-to-run spread of the simulator seeds; a
failure means a change made a headline figure worse, not that the machine was busy (no timing here)."""

from __future__ import annotations

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


def test_shipped_classifiers_on_test_worlds():
    from glassmap.classifier import GlassClassifier
    from glassmap.glass_eval import EvalConfig, evaluate_worlds

    clfs = {m: GlassClassifier.load_default(m) for m in ("context", "baseline")}
    cfg = EvalConfig(generated=6, builtin=("office", "lobby"), seeds=(0,), scans=100)
    res = evaluate_worlds(clfs, cfg, progress=False)
    c, b = res["models"]["context"]["summary"], res["models"]["baseline"]["summary"]
    # README (20 generated test worlds + 4 built-in, seeds 0-2, 200 scans): context balanced accuracy 0.995
    # mean / 0.983 worst, precision 0.884, recall 0.995, ECE 0.006; baseline 0.952 / 0.905, precision 0.417
    assert c["balanced_accuracy_mean"] >= 0.97 and c["balanced_accuracy_worst"] >= 0.94
    assert c["precision_mean"] >= 0.8 and c["recall_mean"] >= 0.9 and c["ece_mean"] <= 0.03
    assert c["balanced_accuracy_mean"] > b["balanced_accuracy_mean"] and c["precision_mean"] > b["precision_mean"]
