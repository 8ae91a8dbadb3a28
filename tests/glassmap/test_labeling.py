"""Labels of a recording from a floor plan: alignment from a rough initial pose, labels against the
simulator's truth, unknown where the plan cannot say."""

from __future__ import annotations

import numpy as np
import pytest

from glassmap.labeling import GLASS, NOT_GLASS, UNKNOWN, LabelingError, beam_labels, label_recording, load_labels


@pytest.fixture(scope="module")
def run():
    from glassmap.sim.dataset import simulate_run
    from glassmap.sim.world import load_world

    world = load_world("office")
    return world, simulate_run(world, route=np.array([[1.2, 1.2], [9.0, 1.2]]), seed=5, scan_rate=10.0, odom_rate=10.0)


def _odom_laser_poses(run, idx):
    """The odometry's base pose at each scan with the simulator's laser mount (odom frame)."""
    from glassmap.labeling import compose

    mount = np.array(run.params["robot"]["laser_offset"], dtype=np.float64)
    base = np.column_stack([np.interp(run.scan_stamps[idx], run.odom_stamps, run.odom_poses[:, k]) for k in range(3)])
    return np.array([compose(b, mount) for b in base])


def test_alignment_and_labels_agree_with_the_simulators_truth(run, tmp_path):
    world, r = run
    idx = np.arange(0, r.n_scans, 3)
    scans = [r.scan(int(i)) for i in idx]
    true = r.laser_poses[idx]
    rough = true[0] + np.array([0.3, -0.25, np.radians(5.0)])
    lab = label_recording(world, scans, _odom_laser_poses(r, idx), rough)
    assert not lab.doubtful.any()
    err = np.hypot(*(lab.poses[:, :2] - true[:, :2]).T)
    assert err.max() < 0.03 and np.abs(np.angle(np.exp(1j * (lab.poses[:, 2] - true[:, 2])))).max() < np.radians(0.5)
    agree, known, glass = 0, 0, 0
    for j, i in enumerate(idx):
        lb = beam_labels(world, scans[j], lab.poses[j])
        k = lb != UNKNOWN
        agree += int(((lb == GLASS) == r.is_glass[i])[k].sum())
        known += int(k.sum())
        glass += int((lb == GLASS).sum())
    assert agree / known > 0.995 and glass > 50
    c = lab.counts
    assert c["glass"] == glass and c["unknown"] < 0.5 * sum(c.values())
    assert lab.x.shape == (lab.y.shape[0], 19) and lab.y.any()
    back = load_labels(lab.save(tmp_path / "l.npz"))
    np.testing.assert_array_equal(back.x, lab.x)
    assert back.counts == lab.counts and back.beams().x.shape == lab.x.shape


def test_returns_off_the_plan_are_unknown(run):
    world, r = run
    scan = r.scan(3)
    pose = r.laser_poses[3]
    scan.ranges = scan.ranges.copy()
    scan.ranges[500:520] = 0.6  # a person in front of the laser: not on the floor plan
    lb = beam_labels(world, scan, pose)
    assert np.all(lb[500:520] == UNKNOWN)
    assert (lb == NOT_GLASS).sum() > 300


def test_a_wrong_initial_pose_is_refused(run):
    world, r = run
    scans = [r.scan(i) for i in range(3)]
    with pytest.raises(LabelingError, match="initial pose"):
        label_recording(world, scans, None, r.laser_poses[0] + np.array([6.0, 3.0, 2.0]))
