"""The online experiment: robust3's margins over direct per kind of map, and (slow) a trial with the pose
graph scores the maps rebuilt from the key scans with and without the loop closures."""

import numpy as np
import pytest

from glassmap.eval.metrics import score_map
from glassmap.pose.experiment import OnlineTrialConfig, margins, run_online_trial


def _s(mean, worst, std):
    return dict(n=3, mean=mean, worst=worst, std=std)


def test_margins_are_relative_gains_and_beating_needs_all_three():
    summary = {"direct": _s(0.20, 0.30, 0.05), "robust3": _s(0.18, 0.27, 0.04),
               "direct@keys": _s(0.20, 0.30, 0.05), "robust3@keys": _s(0.18, 0.31, 0.04)}
    out = {m["maps"]: m for m in margins(summary)}
    assert set(out) == {"online", "keys"}  # no @keys+lc rows: not reported
    np.testing.assert_allclose([out["online"][k] for k in ("mean_gain", "worst_gain", "std_gain")], [0.1, 0.1, 0.2])
    assert out["online"]["beats"] and not out["keys"]["beats"]  # worse in the worst trial
    assert out["keys"]["worst_gain"] < 0


@pytest.mark.slow
def test_trial_with_loop_closure_scores_maps_rebuilt_at_front_end_and_optimised_poses():
    cfg = OnlineTrialConfig(world="glass-corridor", route=None, methods=("direct", "robust3"), loop_closure=True,
                            sigmas=("map", "anchor"), compare_glass_scans=True)
    maps: dict = {}
    rows = run_online_trial(cfg, 0, maps_out=maps)
    names = [r["method"] for r in rows]
    assert set(maps) == set(names) | {"truth", "evaluated"}
    for r in rows:  # the labels handed out are the ones scored
        assert score_map(maps[r["method"]], maps["truth"], maps["evaluated"]).error == r["error"]
    assert names == ["direct", "robust3", "robust3~anchor", "direct@every-online", "robust3@every-online",
                     "direct@keys", "robust3@keys", "direct@keys+lc",
                     "robust3@keys+lc"]  # direct does not read the sigma: no direct~anchor
    for r in rows:
        assert 0.0 <= r["error"] < 0.5 and r["n_cells"] > 100  # the corridor's glass walls scored
        assert r["key_scans"] > 10 and np.isfinite(r["keys_ate"]) and np.isfinite(r["keys_lc_ate"])
        assert r["false_closures"] <= r["closures"]


def test_online_trial_config_refuses_unknown_glass_scans_and_a_zero_step():
    with pytest.raises(ValueError, match="glass_scans"):
        OnlineTrialConfig(glass_scans="all")
    with pytest.raises(ValueError, match="glass_every"):
        OnlineTrialConfig(glass_scans="every", glass_every=0)


def test_false_closures_are_those_off_the_truth_by_more_than_5_cm_or_1_deg():
    from glassmap.pose.backend import Closure
    from glassmap.pose.experiment import _false_closures

    truth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi / 2], [1.0, 1.0, np.pi]])
    cov = np.eye(3)
    right = Closure(0, 2, np.array([1.0, 1.0, np.pi]), cov, 0.0)
    off_xy = Closure(0, 2, np.array([1.06, 1.0, np.pi]), cov, 0.0)
    off_yaw = Closure(1, 2, np.array([1.0, 0.0, np.radians(91.5)]), cov, 0.0)
    assert _false_closures([right], truth) == 0
    assert _false_closures([right, off_xy, off_yaw], truth) == 2


def test_world_margins_per_world_and_the_worst_world_over_them():
    from glassmap.pose.experiment import world_margins

    def rows(world, direct, robust):
        return [dict(world=world, seed=s, method=m, error=e, error_occupied=e, glass_recall=0.9, false_glass_rate=0.0)
                for s, (d, r) in enumerate(zip(direct, robust)) for m, e in (("direct", d), ("robust3", r))]

    a = rows("a", [0.10, 0.20], [0.09, 0.18])  # robust 10 % lower in every trial
    b = rows("b", [0.10, 0.10], [0.12, 0.12])  # robust 20 % higher
    per_world, overall = world_margins(a + b, others=("robust3",))
    assert [(m["world"], m["maps"]) for m in per_world] == [("a", "online"), ("b", "online")]
    assert per_world[0]["mean_gain"] == pytest.approx(0.1) and per_world[1]["mean_gain"] == pytest.approx(-0.2)
    (o,) = overall
    assert o["mean_gain"] == pytest.approx(-0.05) and o["mean_gain_worst"] == pytest.approx(-0.2)
    assert o["mean_gain_worst_world"] == "b" and o["worlds"] == 2 and o["beats"] == 1
    assert (per_world[0]["wins"], per_world[0]["n"]) == (2, 2) and per_world[1]["wins"] == 0
    assert per_world[0]["diff"] == pytest.approx(0.015) and per_world[0]["diff_se"] == pytest.approx(0.005)
    assert per_world[1]["diff"] == pytest.approx(-0.02) and per_world[1]["diff_se"] == pytest.approx(0.0)
    assert (o["wins"], o["trials"]) == (2, 4)


def test_paired_figures_match_trials_by_seed():
    from glassmap.pose.experiment import paired

    rows = [dict(seed=s, method=m, error=e) for s, m, e in
            ((0, "direct", 0.10), (1, "direct", 0.30), (2, "direct", 0.20), (1, "robust3", 0.25), (0, "robust3", 0.12))]
    p = paired(rows, "direct", "robust3")  # seed 2 has no robust3 trial: left out
    assert (p["n"], p["wins"]) == (2, 1) and p["diff"] == pytest.approx(0.015)
    assert p["diff_se"] == pytest.approx(np.std([-0.02, 0.05], ddof=1) / np.sqrt(2))
    assert paired(rows[:1], "direct", "robust3")["n"] == 0


def test_margins_command_prints_the_trials_won_and_the_paired_difference(tmp_path, capsys):
    import csv

    from runtime.cli import main

    path = tmp_path / "online_w.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, ["seed", "world", "method", "maps", "error", "error_occupied", "glass_recall",
                               "false_glass_rate"])
        w.writeheader()
        for s, (d, r) in enumerate([(0.10, 0.09), (0.20, 0.18), (0.10, 0.11)]):
            for m, e in (("direct", d), ("robust3", r)):
                w.writerow(dict(seed=s, world="w.toml", method=m, maps="online", error=e, error_occupied=e,
                                glass_recall=0.9, false_glass_rate=0.0))
    assert main(["pose", "margins", str(path)]) == 0
    out = capsys.readouterr().out
    assert "2 of 3" in out and "+0.67 +- 0.88" in out and "lower error in 2 of 3 trials" in out
