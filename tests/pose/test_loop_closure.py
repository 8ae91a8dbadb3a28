"""Loop closure on synthetic worlds: a drifted loop is closed with correct closures only; a loop the front end
kept consistent is not bent by them; in a featureless corridor driven out and back the closures correct the
sideways position and the heading, not the long axis they do not observe; a closure needs a second, agreeing
one."""

import numpy as np

from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from glassmap.pose.chain import ChainConfig
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.loop_closure import Candidate, LoopCloser, LoopClosureConfig
from glassmap.pose.motion import compose, relative
from glassmap.types import LaserGeometry
from tests.pose.synth import box, corridor, raycast

MOUNT = np.array([0.1, 0.0, 0.0])
GEOM = LaserGeometry()


def _ring() -> np.ndarray:
    """A 20 x 12 m ring corridor round a 14 x 6 m block, with recesses that break its symmetry."""
    return np.concatenate([box(-10.0, -6.0, 10.0, 6.0), box(-7.0, -3.0, 7.0, 3.0), box(-4.0, -6.0, -3.0, -5.5),
                           box(2.0, 5.4, 3.5, 6.0), box(9.4, -1.0, 10.0, 0.5), box(-10.0, 1.0, -9.5, 1.8)])


def _route(waypoints: list[tuple[float, float]], step: float = 0.25) -> np.ndarray:
    """Poses every ``step`` m along straight legs, turning on the spot (10 deg steps) at the corners."""
    out = []
    for (x0, y0), (x1, y1) in zip(waypoints[:-1], waypoints[1:]):
        yaw = np.arctan2(y1 - y0, x1 - x0)
        if out:
            last = out[-1][2]
            turn = np.angle(np.exp(1j * (yaw - last)))
            for k in range(1, int(abs(turn) / np.radians(10))):
                out.append(np.array([x0, y0, last + np.sign(turn) * k * np.radians(10)]))
        n = int(np.hypot(x1 - x0, y1 - y0) / step)
        out += [np.array([x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n, yaw]) for i in range(n)]
    return np.array(out)


def _keys(segments: np.ndarray, truth: np.ndarray, yaw_bias: float, along_bias: float = 0.0,
          front: np.ndarray | None = None) -> list[KeyScan]:
    """Key scans seen from the true poses, placed by a front end that turns ``yaw_bias`` rad too much per
    key scan and overestimates each step by ``along_bias`` (a share), or at the poses ``front``."""
    rng = np.random.default_rng(3)
    if front is None:
        front = [truth[0]]
        for a, b in zip(truth[:-1], truth[1:]):
            rel = relative(a, b)
            rel = rel * np.array([1.0 + along_bias, 1.0, 1.0]) + np.array([0.0, 0.0, yaw_bias])
            front.append(compose(front[-1], rel))
    keys = []
    for i, (t, f) in enumerate(zip(truth, front)):
        r = raycast(segments, compose(t, MOUNT), GEOM.angles, GEOM.range_max)
        r = r + rng.normal(0.0, 0.01, r.shape)
        keys.append(KeyScan(seq=i, stamp=0.5 * i, pose=f, cov=np.eye(3) * 1e-6, odom=np.zeros(3), fused_dims=3,
                            written=True, angles=GEOM.angles, ranges=r, range_max=GEOM.range_max, mount=MOUNT))
    return keys


def _run(keys: list[KeyScan], loop_closure: bool = True) -> GraphBackEnd:
    be = GraphBackEnd(BackEndConfig(loop_closure=loop_closure))
    for k in keys:
        be.add(k)
    return be


def test_drifted_loop_is_closed_with_correct_closures_only():
    truth = _route([(-8.5, -4.5), (8.5, -4.5), (8.5, 4.5), (-8.5, 4.5), (-8.5, -4.5), (0.0, -4.5)])
    keys = _keys(_ring(), truth, yaw_bias=np.radians(0.012))
    front = np.array([k.pose for k in keys])
    assert np.hypot(*(front[-1, :2] - truth[-1, :2])) > 0.15  # the front end's drift at the end

    be = _run(keys)
    assert len(be.closures) >= 2
    assert be.chain_unscaled > 0  # a steady turn is not the drift chain_scale allows: the chain was unscaled
    for c in be.closures:  # every accepted closure is right: within 3 cm and 0.3 deg of the truth
        dxy, dyaw = c.error(truth[c.anchor], truth[c.node])
        assert dxy < 0.03 and dyaw < np.radians(0.3)
    final = be.poses()
    assert np.hypot(*(final[-1, :2] - truth[-1, :2])) < 0.05
    np.testing.assert_allclose(compose(be.correction(), keys[-1].pose), final[-1], atol=1e-9)

    off = _run(keys, loop_closure=False)
    assert not off.closures
    np.testing.assert_allclose(off.poses(), front, atol=1e-6)


def test_a_loop_the_front_end_kept_consistent_is_not_turned_by_a_closure():
    """A front end anchored to its map: each key scan off by its own few millimetres and hundredths of a
    degree, with no drift. A closure at the end that is 0.2 deg off in heading (inside its covariance, as a
    closure against a metre of submap is) must not turn the loop: the optimised poses stay about as close to
    the truth as the front end's, where a random walk of the sequential edges would bend it."""
    truth = _route([(-8.5, -4.5), (8.5, -4.5), (8.5, 4.5), (-8.5, 4.5), (-8.5, -4.5)])
    rng = np.random.default_rng(7)
    noise = rng.normal(0.0, 1.0, truth.shape) * np.array([0.003, 0.003, np.radians(0.03)])
    front = np.array([compose(t, n) for t, n in zip(truth, noise)])
    front[0] = truth[0]
    last = 4 * ((len(truth) - 1) // 4)  # a node the closer is asked about (every check_every = 4th)
    truth, front = truth[:last + 1], front[:last + 1]
    keys = _keys(_ring(), truth, 0.0, front=front)
    closure = Candidate(last, 0.0, front[last], 0, 0, relative(truth[0], truth[last]) + [0.0, 0.0, np.radians(0.2)],
                        np.diag(np.square(LoopClosureConfig().cov_floor)), 1.0)

    def ate(config: BackEndConfig) -> float:
        be = GraphBackEnd(config)
        be.closer.check = lambda store, poses, node, key, travel: [closure] if node == last else []
        for k in keys:
            be.add(k)
        assert len(be.closures) == 1 and be.chain_unscaled == 0
        return float(np.sqrt(np.mean(np.sum((be.poses()[:, :2] - truth[:, :2]) ** 2, axis=1))))

    front_ate = float(np.sqrt(np.mean(np.sum((front[:, :2] - truth[:, :2]) ** 2, axis=1))))
    assert ate(BackEndConfig()) < 1.5 * front_ate
    random_walk = BackEndConfig(chain=ChainConfig(chain_scale=(1.0, 1.0, 1.0)))
    assert ate(random_walk) > 2 * front_ate  # the random walk turns it


def test_featureless_corridor_closures_correct_only_what_they_observe():
    segs = corridor(length=140.0, half_width=1.0)
    truth = _route([(-20.0, 0.0), (5.0, 0.0), (-20.0, 0.0)])
    # 1 % too far on every step, and turning 0.01 deg too much per key scan: 50 cm sideways at the end
    keys = _keys(segs, truth, yaw_bias=np.radians(0.01), along_bias=0.01)
    front = np.array([k.pose for k in keys])
    assert abs(front[-1, 1] - truth[-1, 1]) > 0.4
    be = _run(keys)
    assert len(be.closures) >= 2
    # right where they constrain: within 3 cm, and within 0.4 deg (the old submaps they match are bent by the
    # front end's 0.2 deg per metre); free along the corridor
    for c in be.closures:
        dxy, dyaw = c.error(truth[c.anchor], truth[c.node])
        assert dxy < 0.03 and dyaw < np.radians(0.4)
        assert not np.allclose(c.proj, np.eye(3)) and np.linalg.eigvalsh(c.cov[:2, :2]).max() > 0.5
    final = be.poses()[-1]
    assert abs(final[1] - truth[-1, 1]) < 0.02  # the sideways drift removed
    assert abs(final[0] - truth[-1, 0]) < abs(front[-1, 0] - truth[-1, 0]) + 0.01  # along it: not made worse

    full_only = GraphBackEnd(BackEndConfig(closure=LoopClosureConfig(min_directions=3)))
    for k in keys:
        full_only.add(k)
    assert not full_only.closures  # closing only where all three directions are observed: none here
    assert full_only.closer.stats.rejected.get("unconstrained direction", 0) > 0


def test_a_candidate_is_accepted_only_when_a_second_one_agrees():
    closer = LoopCloser()
    poses = np.zeros((10, 3))

    def cand(node, travel, front, pose):
        return Candidate(node, travel, np.asarray(front, float), 0, 0, np.asarray(pose, float), np.eye(3) * 1e-4, 0.9)

    a = cand(4, 30.0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    good = cand(6, 30.5, (0.5, 0.0, 0.0), (1.5, 0.01, 0.0))  # 1 cm off: agrees
    bad = cand(6, 30.5, (0.5, 0.0, 0.0), (1.6, 0.0, 0.0))  # 10 cm off: the two matches disagree
    assert closer.agree(a, good, poses)
    assert not closer.agree(a, bad, poses)
    assert not closer.agree(a, cand(6, 30.5, (0.5, 0.0, 0.0), (1.5, 0.0, np.radians(1.0))), poses)


def test_candidates_that_constrain_only_part_of_the_pose_are_compared_only_there():
    closer = LoopCloser()
    poses = np.zeros((10, 3))
    along_x = np.diag([0.0, 1.0, 1.0])  # a corridor along x: y and yaw observed

    def cand(node, front, pose):
        return Candidate(node, 30.0 + 0.5 * (node - 4), np.asarray(front, float), 0, 0, np.asarray(pose, float),
                         np.eye(3) * 1e-4, 0.9, along_x)

    a = cand(4, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    assert closer.agree(a, cand(6, (0.5, 0.0, 0.0), (1.6, 0.01, 0.0)), poses)  # 10 cm along it: not observed
    assert not closer.agree(a, cand(6, (0.5, 0.0, 0.0), (1.5, 0.1, 0.0)), poses)  # 10 cm across it


def test_a_chain_gate_outside_0_1_is_refused():
    import pytest

    with pytest.raises(ValueError, match="chain_gate"):
        BackEndConfig(chain_gate=1.5)


def test_a_step_matched_in_fewer_than_three_directions_keeps_its_along_track_noise():
    """Along a corridor the match fixes the sideways position and heading, odometry the step along the heading:
    chain_scale stiffens only what a match measured."""
    from dataclasses import replace

    truth = _route([(-8.5, -4.5), (-6.0, -4.5)])
    keys = _keys(_ring(), truth, 0.0)[:3]
    be = GraphBackEnd(BackEndConfig(loop_closure=False))
    for k in (keys[0], keys[1], replace(keys[2], fused_dims=2)):
        be.add(k)
    sx, sy, syaw = ChainConfig().chain_scale
    full, part = be.seq_cov
    np.testing.assert_allclose(np.diag(be._scaled(0)), np.diag(full) * np.square([sx, sy, syaw]))
    np.testing.assert_allclose(np.diag(be._scaled(1)), np.diag(part) * np.square([1.0, sy, syaw]))
