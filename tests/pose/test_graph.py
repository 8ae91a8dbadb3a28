"""Pose graph on iSAM2: a chain follows its edges; a loop edge pulls a drifted chain back."""

import numpy as np
import pytest

from glassmap.pose.graph import PoseGraph, PoseGraphError, to_tangent
from glassmap.pose.motion import compose, relative

SQUARE = [np.array([2.0, 0.0, np.pi / 2])] * 4  # four legs of a 2 m square, turning left


def _chain(rels, cov=np.diag([1e-4, 1e-4, 1e-4])):
    g = PoseGraph(np.zeros(3), np.diag([1e-8, 1e-8, 1e-8]))
    for r in rels:
        g.add_node(r, cov)
    return g


def test_chain_follows_its_edges():
    g = _chain(SQUARE[:3])
    p = g.refresh()
    assert p.shape == (4, 3)
    np.testing.assert_allclose(p[1], [2.0, 0.0, np.pi / 2], atol=1e-9)
    np.testing.assert_allclose(p[3, :2], [0.0, 2.0], atol=1e-9)


def test_loop_edge_removes_drift_and_shrinks_the_marginal():
    bias = np.array([0.0, 0.0, np.radians(3.0)])  # each leg turns 3 deg too much
    g = _chain([r + bias for r in SQUARE])
    before = g.refresh()[-1]
    assert np.hypot(*before[:2]) > 0.25  # back at the start, but the chain says 0.29 m away
    m_before = g.marginal(4)
    g.add_loop(0, 4, np.zeros(3), np.diag([1e-6, 1e-6, 1e-6]))
    after = g.poses[-1]
    assert np.hypot(*after[:2]) < 0.01
    assert np.trace(g.marginal(4)) < 0.01 * np.trace(m_before)
    assert [e.kind for e in g.edges].count("loop") == 1


def test_to_tangent_rotates_translation_into_the_end_frame():
    cov = np.diag([4.0, 1.0, 0.5])
    out = to_tangent(np.array([1.0, 2.0, np.pi / 2]), cov)
    np.testing.assert_allclose(out, np.diag([1.0, 4.0, 0.5]), atol=1e-12)


def test_loop_edge_to_a_missing_node_is_an_error():
    g = _chain(SQUARE[:1])
    with pytest.raises(PoseGraphError, match="existing nodes"):
        g.add_loop(0, 5, np.zeros(3), np.eye(3))
    with pytest.raises(PoseGraphError, match="no node"):
        g.marginal(7)


def test_relative_edge_convention_matches_motion_relative():
    a, b = np.array([1.0, -2.0, 0.4]), np.array([3.0, 0.5, -1.0])
    g = PoseGraph(a, np.diag([1e-8, 1e-8, 1e-8]))
    g.add_node(relative(a, b), np.diag([1e-4, 1e-4, 1e-4]))
    np.testing.assert_allclose(g.refresh()[1], b, atol=1e-9)
    np.testing.assert_allclose(compose(a, relative(a, b)), b, atol=1e-12)


def test_reweighted_edges_give_the_solution_of_a_graph_built_with_them():
    bias = np.array([0.0, 0.0, np.radians(3.0)])
    rels = [r + bias for r in SQUARE]
    tight, loose = np.diag([1e-6, 1e-6, 1e-8]), np.diag([1e-4, 1e-4, 1e-4])
    g = _chain(rels, tight)
    g.add_loop(0, 4, np.zeros(3), np.diag([1e-6, 1e-6, 1e-6]))
    stiff = g.poses
    g.reweight([loose] * 4)
    fresh = _chain(rels, loose)
    fresh.add_loop(0, 4, np.zeros(3), np.diag([1e-6, 1e-6, 1e-6]))
    np.testing.assert_allclose(g.poses, fresh.poses, atol=1e-6)
    assert np.abs(g.poses - stiff).max() > 0.01  # the weights moved the solution
    with pytest.raises(PoseGraphError, match="sequential edges"):
        g.reweight([loose] * 3)


def test_newest_covariance_is_the_marginal_in_the_map_frame_without_handing_over_the_batch():
    legs = [np.array([0.5, 0.0, 0.3])] * 13  # 13 nodes after the first: one batch of 10 handed over, 3 pending
    g = PoseGraph(np.zeros(3), np.diag([1e-8, 1e-8, 1e-8]), batch=10)
    for r in legs:
        g.add_node(r, np.diag([1e-4, 4e-4, 1e-5]))
    pending = g.poses
    cov = g.newest_covariance()
    np.testing.assert_array_equal(g.poses, pending)  # nothing re-solved
    p = g.refresh()[-1]
    c, s = np.cos(p[2]), np.sin(p[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(cov, rot @ g.marginal(13) @ rot.T, rtol=1e-6, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    g.add_loop(0, 13, relative(np.zeros(3), p), np.diag([1e-6, 1e-6, 1e-6]))
    assert np.trace(g.newest_covariance()) < 0.1 * np.trace(cov)  # a closure to the start: it shrinks
