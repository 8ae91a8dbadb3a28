"""Scoring the online map against the blueprint: grid alignment and the paper's per-cell rule."""

from __future__ import annotations

import csv
from types import SimpleNamespace

import numpy as np
import pytest

from glassmap.glass import GlassMap
from glassmap.grid import MapGrid, OccupancyGrid
from glassmap.sim.blueprint import Blueprint
from glassmap.sim.world import load_world
from runtime.evaluate import evaluate_map


def perfect_mapper(world, shift_cells=(7, -3), glass_value=3.0):
    """A map grid offset from the blueprint's by ``shift_cells`` (x, y), holding the blueprint exactly."""
    bp = Blueprint.from_world(world, resolution=0.05)
    h, w = bp.labels.shape
    pad = 20
    origin = bp.origin - 0.05 * (np.array(shift_cells) + pad)
    grid = MapGrid(0.05, origin=tuple(origin), shape=(h + 2 * pad + 10, w + 2 * pad + 10))
    occ = OccupancyGrid(grid)
    glass = GlassMap(grid)
    y0, x0 = pad + shift_cells[1], pad + shift_cells[0]
    occ.log_odds[y0:y0 + h, x0:x0 + w] = np.where(bp.labels > 0, 3.0, -3.0)
    glass.log_odds[y0:y0 + h, x0:x0 + w] = np.where(bp.labels == 2, glass_value, -3.0)
    return SimpleNamespace(mapper=SimpleNamespace(grid=grid, occupancy=occ, glass=glass)), bp


@pytest.fixture(scope="module")
def world():
    return load_world("office")


def test_a_map_equal_to_the_blueprint_scores_zero(world):
    proc, bp = perfect_mapper(world)
    ev = evaluate_map(proc.mapper, world, seen=np.ones(bp.labels.shape, bool))
    assert ev.error == 0.0 and ev.glass_recall == 1.0 and ev.false_glass_rate == 0.0
    assert ev.n_glass > 100 and ev.n_wall > 100 and ev.seen_from == "simulator"


def test_glass_called_wall_counts_every_glass_cell(world):
    proc, bp = perfect_mapper(world, glass_value=-3.0)
    ev = evaluate_map(proc.mapper, world, seen=np.ones(bp.labels.shape, bool))
    assert ev.error == pytest.approx(ev.n_glass / ev.n_cells)
    assert ev.glass_recall == 0.0


def test_only_seen_cells_count(world):
    proc, bp = perfect_mapper(world, glass_value=0.0)  # undecided everywhere on glass
    seen = np.zeros(bp.labels.shape, bool)
    assert evaluate_map(proc.mapper, world, seen=seen).n_cells == 0
    seen[:, : bp.labels.shape[1] // 2] = True
    ev = evaluate_map(proc.mapper, world, seen=seen)
    assert 0 < ev.n_cells and ev.error == pytest.approx(ev.n_glass / ev.n_cells) and ev.unregistered > 0


def test_a_map_shifted_off_the_blueprint_is_realigned(world):
    proc, bp = perfect_mapper(world)
    g = proc.mapper.grid
    g.origin = g.origin + np.array([0.10, -0.05])  # the map sits 2 cells right, 1 cell down of the truth
    ev = evaluate_map(proc.mapper, world, seen=np.ones(bp.labels.shape, bool))
    assert ev.error > 0.5  # the strict per-cell rule counts the shifted walls as unregistered
    assert ev.shift_cells == (-2, 1)
    assert ev.aligned is not None and ev.aligned.error == 0.0
    assert "after aligning" in ev.describe()
    assert evaluate_map(proc.mapper, world, seen=np.ones(bp.labels.shape, bool), max_shift=0).aligned is None


def test_trajectory_is_scored_at_the_same_scans():
    from runtime.evaluate import evaluate_trajectory

    truth = np.array([[10, 0.0, 0.0, 0.0], [35, 0.1, 0.0, 0.0], [60, 0.2, 0.0, 0.1], [85, 0.3, 0.0, 0.1]])
    # estimates of scans 35 and 85 (scan 60 was dropped; 999 has no truth), 3 cm and 4 cm off
    est = np.array([[35, 0.13, 0.0, 0.0], [999, 5.0, 5.0, 0.0], [85, 0.3, 0.04, 0.1 + 2 * np.pi]])
    ev = evaluate_trajectory(est, truth)
    assert ev.n == 2
    assert ev.final_error == pytest.approx(0.04) and ev.max_error == pytest.approx(0.04)
    assert ev.ate == pytest.approx(np.sqrt((0.03 ** 2 + 0.04 ** 2) / 2))
    assert ev.yaw_rms == pytest.approx(0.0, abs=1e-12)  # headings compared modulo a turn
    np.testing.assert_array_equal(ev.final_true, [0.3, 0.0, 0.1])
    assert evaluate_trajectory(est[1:2], truth) is None


def test_pose_graph_is_scored_at_its_key_scans_and_closures_against_the_truth(tmp_path):
    from glassmap.pose.backend import Closure
    from runtime.evaluate import evaluate_graph

    truth = np.array([[10, 0.0, 0.0, 0.0], [35, 1.0, 0.0, 0.0], [60, 2.0, 0.0, 0.0], [85, 2.0, 1.0, np.pi / 2]])
    keys = np.array([10.0, 60.0, np.nan, 85.0])  # the third key scan has no true pose
    poses = np.array([[0.0, 0.0, 0.0], [2.03, 0.0, 0.0], [9.0, 9.0, 0.0], [2.0, 1.04, np.pi / 2]])
    good = Closure(anchor=0, node=1, pose=np.array([2.01, 0.0, 0.0]), cov=np.eye(3), stamp=0.0)
    # 10 cm off along x, which a partial closure that constrains only y does not count
    partial = Closure(anchor=0, node=3, pose=np.array([2.1, 1.0, np.pi / 2]), cov=np.eye(3), stamp=0.0,
                      proj=np.diag([0.0, 1.0, 1.0]))
    wrong = Closure(anchor=1, node=3, pose=np.array([0.0, 1.0, np.radians(92.0)]), cov=np.eye(3), stamp=0.0)
    unscored = Closure(anchor=2, node=3, pose=np.zeros(3), cov=np.eye(3), stamp=0.0)
    ev = evaluate_graph(keys, poses, (good, partial, wrong, unscored), truth)
    assert ev.n == 3 and ev.ate == pytest.approx(np.sqrt((0.03 ** 2 + 0.04 ** 2) / 3))
    assert ev.closures == 3 and ev.false == 1  # the 2 deg one
    assert ev.worst_xy == pytest.approx(0.01) and ev.worst_yaw == pytest.approx(np.radians(2.0))
    assert "1 false (worst 1.0 cm, 2.00 deg" in ev.describe()
    assert [(r["anchor"], r["node"], r["directions"], r["false"]) for r in ev.rows] == [
        (0, 1, 3, False), (0, 3, 2, False), (1, 3, 3, True)]
    assert np.isnan(ev.rows[0]["node_stamp"])  # no stamps given
    stamped = evaluate_graph(keys, poses, (wrong,), truth, stamps=np.array([0.0, 0.5, 1.0, 1.5]))
    path = tmp_path / "closures.csv"
    stamped.write_csv(path)
    with open(path) as f:
        (row,) = list(csv.DictReader(f))
    assert (row["anchor_stamp"], row["node_stamp"], row["false"]) == ("0.5", "1.5", "True")
    assert float(row["error_yaw"]) == pytest.approx(np.radians(2.0))
    assert "no loop closure" in evaluate_graph(keys, poses, (), truth).describe()
    assert evaluate_graph(np.full(4, np.nan), poses, (), truth) is None
