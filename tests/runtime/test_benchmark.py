"""The generalisation benchmark end to end on one tiny world with minimal settings: every part runs, the
CSV / JSON files are written with the expected keys; aggregation picks the mean and the worst world."""

import csv
import json

import pytest

from runtime.benchmark import METRICS, BenchmarkConfig, aggregate, run_benchmark

TINY = """
name = "tiny"
default_route = "main"
[routes.main]
waypoints = [[1.0, 1.5], [4.0, 1.5]]
[[polylines]]
points = [[0, 0], [6, 0], [6, 3], [0, 3]]
closed = true
material = "wall"
[[panes]]
a = [1.0, 3.0]
b = [5.0, 3.0]
pane_width = 1.3
[[boxes]]
center = [3.0, 4.0]
size = [1.0, 0.5]
material = "object"
[[polylines]]
points = [[0, 3], [0, 5], [6, 5], [6, 3]]
material = "wall"
"""


def test_benchmark_on_a_tiny_world_end_to_end(tmp_path):
    world = tmp_path / "tiny.toml"
    world.write_text(TINY)
    cfg = BenchmarkConfig(generated=0, worlds=(str(world),), seeds=(0,), classifier_poses=5, trials=1,
                          demo_speed=2.0, demo_duration=10.0, out_dir=str(tmp_path / "out"))
    rep = run_benchmark(cfg, workers=1, progress=False, figure=False)
    assert rep.failures == []
    (row,) = rep.worlds
    for k in METRICS:
        assert k in row, k
    for k in ("clf_glass_recall", "map_error_true_poses", "exp_robust3_mean", "pose_ate_rmse", "demo_error"):
        assert 0.0 <= row[k] < 10.0, k
    assert 0.0 <= row["demo_final_sigma"] < 3.0 and row["demo_silent_divergence"] == 0.0
    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert "| tiny | file |" in (tmp_path / "out" / "summary.md").read_text()
    assert doc["worlds"][0]["world"] == "tiny" and "files" in doc["summary"]
    assert doc["summary"]["files"]["pose_ate_rmse"]["worst_world"] == "tiny"
    with open(tmp_path / "out" / "per_run.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["part"] for r in rows} == {"classifier", "map", "experiment", "pose", "demo"}
    assert {r["method"] for r in rows if r["part"] == "experiment"} == {"direct", "robust3", "robust5"}


def test_aggregate_mean_and_worst_world():
    rows = [dict(world="a", kind="office", pose_ate_rmse=0.01, clf_glass_recall=0.9),
            dict(world="b", kind="lobby", pose_ate_rmse=0.05, clf_glass_recall=0.7),
            dict(world="office", kind="built-in", pose_ate_rmse=0.02, clf_glass_recall=0.95)]
    s = aggregate(rows)
    assert s["generated"]["pose_ate_rmse"]["mean"] == pytest.approx(0.03)
    assert s["generated"]["pose_ate_rmse"]["worst_world"] == "b"
    assert s["generated"]["clf_glass_recall"]["worst"] == pytest.approx(0.7)  # higher is better: min
    assert s["built-in"]["pose_ate_rmse"]["worlds"] == 1 and s["all"]["pose_ate_rmse"]["worlds"] == 3


def test_config_rejects_unknown_parts_and_test_seed_range():
    with pytest.raises(ValueError, match="unknown part"):
        BenchmarkConfig(parts=("nope",))
    with pytest.raises(ValueError, match="0-100"):
        BenchmarkConfig(generated=101)


def test_demo_part_reports_the_final_error_in_sigma_with_the_pose_graph(tmp_path):
    """With --demo-loop-closure the demo runs the pose graph; each run says how many sigma its final estimate
    is off and whether it diverged silently (more than 3 sigma off without a lost-track stop)."""
    from runtime.benchmark import Task, _demo

    world = tmp_path / "tiny.toml"
    world.write_text(TINY)
    cfg = BenchmarkConfig(generated=0, worlds=(str(world),), seeds=(0,), demo_speed=2.0, demo_duration=6.0,
                          demo_loop_closure=True, parts=("demo",), out_dir=str(tmp_path / "out"))
    (row,) = _demo(Task("tiny", str(world), "file", "demo", 0), cfg)
    assert row["closures"] == 0 and row["false_closures"] == 0  # a 3 m route closes no loop
    assert row["worst_closure_xy"] == 0.0 and row["worst_closure_yaw"] == 0.0  # (m, rad) scored: none
    assert 0.0 <= row["final_sigma"] < 3.0 and row["silent_divergence"] == 0.0 and not row["stopped_on_pose"]
    # no closure: the pose is the front end's (its sigma is the graph's, from the chain of key scans)
    assert row["final_error"] == pytest.approx(row["final_pose_error"], abs=1e-9)
    # the maps the pose graph rebuilt at its final poses are scored too (issue 17): without a closure they are
    # the online maps rebuilt from the same key scans at the same poses
    assert row["corrected_error"] == pytest.approx(row["error"], abs=0.02)


def test_pose_part_with_the_pose_graph_reports_the_corrected_estimates_consistency(tmp_path):
    """--pose-loop-closure: each pose run also scores the estimate corrected by the pose graph (issue 20, item
    1); without it those columns are NaN."""
    from runtime.benchmark import Task, _pose

    world = tmp_path / "tiny.toml"
    world.write_text(TINY)
    task = Task("tiny", str(world), "file", "pose", 0)
    on = BenchmarkConfig(generated=0, worlds=(str(world),), seeds=(0,), pose_loop_closure=True, parts=("pose",))
    (row,) = _pose(task, on)
    assert row["lc_nees_mean"] > 0.0 and 0.0 < row["lc_inside_95"] <= 1.0
    assert row["lc_closures"] == 0 and row["lc_ate_rmse"] == pytest.approx(row["ate_rmse"])  # nothing closed
    (off,) = _pose(task, BenchmarkConfig(generated=0, worlds=(str(world),), seeds=(0,), parts=("pose",)))
    assert off["lc_nees_mean"] != off["lc_nees_mean"] and off["nees_mean"] == pytest.approx(row["nees_mean"])
