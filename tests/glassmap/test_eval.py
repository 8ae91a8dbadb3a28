"""The experiment's parts: pose-error statistics, map and classifier metrics with known numbers, a quick
trial, and the `glassmap glass experiment` quick mode."""

import math

import numpy as np
import pytest

from glassmap.eval.metrics import binary_report, expected_calibration_error, roc_auc, score_map
from glassmap.eval.pose_error import PoseErrorModel


def test_pose_error_has_the_configured_std_and_correlation():
    m = PoseErrorModel(sigma_xy=0.05, sigma_theta=math.radians(1.0), tau=2.0)
    t = np.arange(200_000) * 0.1
    e = m.sample(t, np.random.default_rng(0))
    assert e[:, 0].std() == pytest.approx(0.05, rel=0.05)
    assert e[:, 1].std() == pytest.approx(0.05, rel=0.05)
    assert e[:, 2].std() == pytest.approx(math.radians(1.0), rel=0.05)
    lag1 = np.corrcoef(e[:-1, 0], e[1:, 0])[0, 1]
    assert lag1 == pytest.approx(math.exp(-0.1 / 2.0), abs=0.01)
    white = PoseErrorModel(0.02, 0.0, tau=0.0).sample(t[:50_000], np.random.default_rng(1))
    assert abs(np.corrcoef(white[:-1, 0], white[1:, 0])[0, 1]) < 0.02
    assert np.all(white[:, 2] == 0)
    assert m.beam_sigma(np.array([0.0, 10.0, np.nan])) == pytest.approx(
        [0.05, math.hypot(0.05, 10 * math.radians(1.0)), 0.05])


def test_score_map_known_numbers():
    truth = np.array([[1, 1, 2, 2, 0]])
    mask = np.ones_like(truth, dtype=bool)
    # wall right, wall labelled glass, glass right, glass not occupied, free cell ignored
    labels = np.array([[0, 1, 1, -2, 1]])
    s = score_map(labels, truth, mask)
    assert s.n_cells == 4 and s.n_glass == 2 and s.n_wall == 2
    assert s.error == pytest.approx(0.5)
    assert s.glass_recall == pytest.approx(0.5) and s.false_glass_rate == pytest.approx(0.5)
    assert s.unregistered == pytest.approx(0.25)
    assert s.error_occupied == pytest.approx(1 / 3)
    undecided = score_map(np.array([[-1, -1, -1, -1, -1]]), truth, mask)
    assert undecided.error == 1.0


def test_classifier_metrics_known_numbers():
    y = np.array([1, 1, 0, 0], dtype=bool)
    assert roc_auc(y, np.array([0.9, 0.4, 0.6, 0.1])) == pytest.approx(0.75)
    assert roc_auc(y, np.array([0.5, 0.5, 0.5, 0.5])) == pytest.approx(0.5)
    r = binary_report(y, np.array([0.9, 0.4, 0.6, 0.1]))
    assert r.precision == pytest.approx(0.5) and r.recall == pytest.approx(0.5)
    assert r.balanced_accuracy == pytest.approx(0.5)
    # perfectly calibrated bins -> 0; always-0.9 on a 50/50 set -> 0.4
    assert expected_calibration_error(y, np.array([1.0, 1.0, 0.0, 0.0])) == pytest.approx(0.0)
    assert expected_calibration_error(y, np.full(4, 0.9)) == pytest.approx(0.4)


def test_quick_trial_scores_every_method_and_zero_sigma_ties():
    from glassmap.eval.trial import TrialConfig, run_trial

    cfg = TrialConfig(duration=8.0, scan_rate=5.0, methods=("direct", "robust3", "robust5-endpoint"),
                      pose_error=PoseErrorModel(0.0, 0.0))
    r = run_trial(cfg, seed=3)
    assert r.n_scans == 40
    for s in r.scores.values():
        assert 0.0 <= s.error <= 1.0 and s.n_cells > 50
    # without pose error robust registration with decay from c_hat equals direct registration
    assert r.scores["direct"].error == r.scores["robust3"].error
    with pytest.raises(ValueError, match="unknown method"):
        TrialConfig(methods=("magic",))


def test_eval_cli_quick_mode(tmp_path):
    from runtime.cli import main

    rc = main(["glass", "experiment", "--trials", "2", "--duration", "5", "--methods", "direct,robust3", "--workers", "2",
               "--out", str(tmp_path)])
    assert rc == 0
    rows = (tmp_path / "trials.csv").read_text().splitlines()
    assert len(rows) == 1 + 2 * 2 and rows[0].startswith("trial,seed,world")
    assert (tmp_path / "boxplot.png").stat().st_size > 1000


def test_map_poses_truth_keeps_the_pose_error_out_of_the_occupancy_grid():
    """map_poses="truth": the occupancy grid is the same whatever the pose error (only the registration
    sees it); "estimate": the pose error moves the walls of the occupancy grid too."""
    from glassmap.eval.trial import TrialConfig, build_maps_for_export

    def occupancy(sigma, map_poses):
        cfg = TrialConfig(duration=5.0, scan_rate=5.0, pose_error=PoseErrorModel(sigma, 0.0), map_poses=map_poses)
        return build_maps_for_export(cfg, seed=2).occupancy.log_odds

    exact = occupancy(0.0, "truth")
    assert np.array_equal(occupancy(0.05, "truth"), exact)
    assert not np.array_equal(occupancy(0.05, "estimate"), exact)
    with pytest.raises(ValueError, match="map_poses"):
        TrialConfig(map_poses="slam")
