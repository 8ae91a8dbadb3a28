"""The chain of key scans: the drift the front end reports is the pose graph's marginal without closures."""

import numpy as np

from glassmap.pose.backend import BackEndConfig, GraphBackEnd
from dataclasses import replace

from glassmap.pose.chain import ChainConfig, DriftChain, psd_min
from glassmap.pose.keyscan import KeyScan
from glassmap.pose.motion import compose


JUMP = np.array([0.3, -0.2, np.radians(3.0)])  # a relocalisation (map frame)


def _key(i: int, pose: np.ndarray, fused_dims: int = 3, jump: np.ndarray | None = None) -> KeyScan:
    return KeyScan(seq=i, stamp=0.1 * i, pose=np.asarray(pose, dtype=np.float64), cov=np.diag([1e-5, 4e-5, 1e-6]),
                   odom=np.zeros(3), fused_dims=fused_dims, written=True, angles=np.zeros(1), ranges=np.ones(1),
                   range_max=30.0, mount=np.zeros(3), jump=jump)


def _keys(n: int, jump_at: int | None = None) -> list[KeyScan]:
    """Key scans 5 cm apart on an arc (1 deg per step); every 7th matched in two directions only, every 11th
    placed by odometry alone; the one ``jump_at`` ended a lost track by a jump of JUMP."""
    poses = [np.zeros(3)]
    for _ in range(n - 1):
        poses.append(compose(poses[-1], np.array([0.05, 0.0, np.radians(1.0)])))
    return [_key(i, p, 0 if i % 11 == 10 else 2 if i % 7 == 6 else 3, JUMP if i == jump_at else None)
            for i, p in enumerate(poses)]


def test_the_chain_is_the_pose_graphs_marginal_without_closures():
    chain = DriftChain(ChainConfig(), np.eye(3) * 1e-6)  # the graph's prior on its first node
    backend = GraphBackEnd(BackEndConfig(loop_closure=False))
    for key in _keys(60, jump_at=25):
        chain.add(key)
        backend.add(key)
        np.testing.assert_allclose(chain.cov, backend.latest().cov, rtol=1e-6, atol=1e-13)


def test_the_chain_grows_from_the_newest_key_scan_with_the_motion_since():
    cfg = ChainConfig(scale_sigma=0.0)
    chain = DriftChain(cfg, np.eye(3) * 1e-6)
    assert np.array_equal(chain.covariance_at(np.ones(3), 5.0), np.eye(3) * 1e-6)  # before any key scan
    keys = _keys(30)
    for key in keys:
        chain.add(key)
    last = keys[-1]
    at_key = chain.covariance_at(last.pose, last.stamp)  # the key scan itself: its drift and the floor
    np.testing.assert_allclose(at_key, chain.cov + np.diag(np.square(cfg.min_sigma)), atol=1e-15)
    ahead = chain.covariance_at(compose(last.pose, np.array([1.0, 0.0, 0.0])), last.stamp + 2.0)
    assert np.all(np.diag(ahead) > np.diag(at_key))  # a metre of odometry, and the heading's lever arm


def test_a_chain_of_matched_steps_is_stiffer_than_odometry():
    keys = _keys(40)
    scaled, odometry = DriftChain(ChainConfig(), np.zeros((3, 3))), DriftChain(ChainConfig(), np.zeros((3, 3)))
    for key in keys:
        scaled.add(key)
        odometry.add(_key(key.seq, key.pose, 0))
    assert np.all(np.diag(scaled.cov) < np.diag(odometry.cov))


def test_the_maps_scale_error_grows_with_the_displacement_from_the_start():
    """The map's scale error (scale_sigma) adds (scale_sigma d)(scale_sigma d)^T, d the position's displacement
    from the first key scan: nothing at the start, along d only, and back to nothing on returning there."""
    keys = _keys(30)
    plain = DriftChain(ChainConfig(scale_sigma=0.0), np.eye(3) * 1e-6)
    scaled = DriftChain(ChainConfig(), np.eye(3) * 1e-6)
    for key in keys:
        plain.add(key)
        scaled.add(key)
    sigma = ChainConfig().scale_sigma
    assert sigma > 0.0
    last = keys[-1]
    for pose, stamp in ((last.pose, last.stamp), (np.array([3.0, 4.0, 0.2]), last.stamp + 1.0),
                        (keys[0].pose, last.stamp + 2.0)):
        d = sigma * (pose[:2] - keys[0].pose[:2])
        extra = scaled.covariance_at(pose, stamp) - plain.covariance_at(pose, stamp)
        np.testing.assert_allclose(extra[:2, :2], np.outer(d, d), atol=1e-15)
        assert np.all(extra[2] == 0.0) and np.all(extra[:, 2] == 0.0)


def test_a_relocalisation_adds_its_jump_to_the_chain_unscaled():
    """The step to a key scan that ended a lost track carries the outer product of its jump's translation (not
    shrunk by chain_scale; the heading, which later matches measure, is left out): the chain's covariance
    after it exceeds the one without the jump by exactly that."""
    plain, jumped = DriftChain(ChainConfig(), np.eye(3) * 1e-6), DriftChain(ChainConfig(), np.eye(3) * 1e-6)
    for a, b in zip(_keys(26), _keys(26, jump_at=25)):
        plain.add(a)
        jumped.add(b)
    shift = np.array([JUMP[0], JUMP[1], 0.0])
    np.testing.assert_allclose(jumped.cov - plain.cov, np.outer(shift, shift), atol=1e-12)


def test_psd_min_keeps_the_smaller_variance_along_every_direction():
    rng = np.random.default_rng(3)
    for _ in range(20):
        ma, mb = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        a, b = ma @ ma.T + 1e-3 * np.eye(3), mb @ mb.T
        m = psd_min(a, b)
        assert np.linalg.eigvalsh(a - m).min() > -1e-9 and np.linalg.eigvalsh(b - m).min() > -1e-9
        np.testing.assert_allclose(psd_min(a, 4.0 * a), a, atol=1e-12)  # b wider everywhere: a
    np.testing.assert_allclose(psd_min(np.diag([4.0, 1.0, 1.0]), np.diag([1.0, 9.0, 1.0])), np.diag([1.0, 1.0, 1.0]))


def _lap(n: int, laps: int) -> list[KeyScan]:
    """Key scans 0.5 m apart around a square of side n / 4 * 0.5 m, ``laps`` times."""
    side = n // 4
    poses = [np.zeros(3)]
    for i in range(1, n * laps):
        turn = np.pi / 2 if i % side == 0 else 0.0
        poses.append(compose(poses[-1], np.array([0.5, 0.0, turn])))
    return [_key(i, p) for i, p in enumerate(poses)]


def test_coming_back_onto_older_map_places_the_key_scan_against_it():
    """A key scan whose matched points lie on cells placed by key scans a lap earlier is as uncertain as those
    (carried to it) plus its own error relative to the map, not more: over three laps the chain stops growing
    where each lap begins. Matched on recent cells only (exploring), it compounds its steps as before."""
    n = 80  # one lap: 40 m
    keys = _lap(n, 3)
    plain, revisits = DriftChain(ChainConfig(), np.eye(3) * 1e-6), DriftChain(ChainConfig(), np.eye(3) * 1e-6)
    covs_plain, covs = [], []
    for k in keys:
        plain.add(k)
        # the points land on cells placed by the key scans at this place a lap before, if there was one
        anchors = np.full(50, k.seq - n) if k.seq >= n else np.full(50, max(k.seq - 1, 0))
        revisits.add(replace(k, anchors=anchors))
        covs_plain.append(plain.cov)
        covs.append(revisits.cov)
    assert revisits.revisits == 2 * n
    np.testing.assert_allclose(covs[:n], covs_plain[:n])  # the first lap: exploring, the steps compounded
    for i in range(n, 3 * n):
        before = covs[i - n]
        assert np.linalg.eigvalsh(before + keys[i].cov - covs[i]).min() > -1e-12  # no wider than a lap before
        assert np.linalg.eigvalsh(covs_plain[i] - covs[i]).min() > -1e-12  # nor than the steps compounded
    assert np.trace(covs_plain[-1]) > 2.0 * np.trace(covs[-1])


def test_a_partial_match_on_older_map_bounds_only_the_directions_it_constrained():
    """Matched in y and yaw only (a corridor along x, map frame) on cells placed a lap before: y and yaw are
    placed against them, x keeps the compounded steps; a relocalisation's jump stays in."""
    n = 80
    keys = _lap(n, 2)
    shift = np.array([JUMP[0], JUMP[1], 0.0])
    y_yaw = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    chains = {name: DriftChain(ChainConfig(), np.eye(3) * 1e-6) for name in ("steps", "partial", "full", "jumped")}
    for k in keys:
        anchors = np.full(50, k.seq - n) if k.seq >= n else None
        dims = 3 if anchors is None else 2
        chains["steps"].add(replace(k, fused_dims=dims))
        chains["partial"].add(replace(k, anchors=anchors, fused_dims=dims,
                                      constrained=None if anchors is None else y_yaw))
        chains["full"].add(replace(k, anchors=anchors))
        chains["jumped"].add(replace(k, anchors=anchors, jump=JUMP if k.seq == 20 else None))
        steps, partial = chains["steps"].cov, chains["partial"].cov
        assert np.linalg.eigvalsh(steps - partial).min() > -1e-12  # never wider than the steps compounded
    assert chains["partial"].revisits == chains["full"].revisits == chains["jumped"].revisits == n
    steps, partial, full = chains["steps"].cov, chains["partial"].cov, chains["full"].cov
    assert partial[0, 0] > 0.9 * steps[0, 0] and partial[0, 0] > 2.0 * full[0, 0]  # x: the steps'
    assert partial[1, 1] < 0.5 * steps[1, 1] and partial[2, 2] < 0.8 * steps[2, 2]  # y, yaw: the older map's
    assert np.linalg.eigvalsh(chains["jumped"].cov - np.outer(shift, shift)).min() > -1e-12  # the jump stays in
