"""``glassmap glass label``: per-beam glass labels for a recording from a floor plan (a world file).

Reads the recording's scans and odometry (MCAP of ``glassmap run`` / ``demo``, ROS 1 / ROS 2 bags), gives
each scan the odometry pose of the laser (base pose interpolated at the scan's stamp, then the laser
mount), and hands them to ``glassmap.labeling.label_recording`` with the rough initial pose from the
command line. Writes the labelled beams (.npz) for ``glassmap glass train --labelled`` and ``glassmap
glass eval --labelled``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from glassmap.cli_args import add_no_progress


def _triple(text: str) -> tuple[float, float, float]:
    try:
        x, y, yaw = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected x,y,yaw_deg (m, m, degrees), got {text!r}") from None
    return x, y, math.radians(yaw)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="a recording: .mcap (glassmap run / demo), ROS 1 .bag, ROS 2 bag")
    p.add_argument("--world", required=True,
                   help="the floor plan: a .toml world file (walls and glass polylines) or a built-in world")
    p.add_argument("--initial-pose", type=_triple, required=True, metavar="X,Y,YAW_DEG",
                   help="rough pose of the robot (base) at the first scan in the plan's frame (m, m, degrees); "
                   "within about 0.5 m and 8 degrees")
    p.add_argument("--laser-mount", type=_triple, default=(0.1, 0.0, 0.0), metavar="X,Y,YAW_DEG",
                   help="laser pose in the base frame (m, m, degrees) (default: 0.1,0,0, the runtime's)")
    p.add_argument("--every", type=int, default=1, help="label every n-th scan (default: %(default)s)")
    p.add_argument("--out", default=None, help="labels file (default: out/labels/<recording name>.npz)")
    add_no_progress(p)


def read_recording(path: str) -> tuple[list, np.ndarray | None]:
    """Scans and the odometry base pose (x, y, yaw in the odom frame) at each scan's stamp (None: the
    recording has no odometry)."""
    from glassmap.types import Odometry, Scan
    from runtime.readers import iter_messages

    scans, odom = [], []
    for m in iter_messages(path):
        if isinstance(m, Scan):
            scans.append(m)
        elif isinstance(m, Odometry):
            odom.append((m.stamp, m.x, m.y, m.yaw))
    if not odom:
        return scans, None
    o = np.array(sorted(odom))
    stamps = np.array([s.stamp for s in scans])
    yaw = np.unwrap(o[:, 3])
    base = np.column_stack([np.interp(stamps, o[:, 0], o[:, 1]), np.interp(stamps, o[:, 0], o[:, 2]),
                            np.interp(stamps, o[:, 0], yaw)])
    return scans, base


def cmd(args) -> int:
    from tqdm import tqdm

    from glassmap.labeling import LabelingError, compose, label_recording
    from glassmap.sim.world import WorldFileError, load_world
    from runtime.readers import ReplayInputError

    if args.every < 1:
        print("error: --every must be >= 1", file=sys.stderr)
        return 2
    try:
        world = load_world(args.world)
        scans, base = read_recording(args.recording)
    except (WorldFileError, ReplayInputError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    scans = scans[:: args.every]
    mount = np.asarray(args.laser_mount)
    odom_laser = None
    if base is not None:
        odom_laser = np.array([compose(b, mount) for b in base[:: args.every]])
    else:
        print("no odometry in the recording: each scan starts from the previous one's pose", file=sys.stderr)
    init = compose(np.asarray(args.initial_pose), mount)
    bar = tqdm(total=len(scans), desc="aligning + labelling", unit="scan", disable=args.no_progress)
    try:
        labels = label_recording(world, scans, odom_laser, init, progress=bar)
    except LabelingError as e:
        bar.close()
        print(f"error: {e}", file=sys.stderr)
        return 2
    bar.close()
    out = Path(args.out) if args.out else Path("out") / "labels" / (Path(args.recording).stem + ".npz")
    labels.save(out)
    c = labels.counts
    total = max(sum(c.values()), 1)
    print(f"{len(scans)} scans, {int(labels.doubtful.sum())} doubtful (alignment); median inlier share "
          f"{np.median(labels.inlier_share):.2f}, median RMS {np.median(labels.rms[np.isfinite(labels.rms)]) * 100:.1f} cm")
    print(f"beams: {c['glass']} glass, {c['not_glass']} not glass, {c['unknown']} unknown "
          f"({c['unknown'] / total:.0%}); {labels.y.shape[0]} labelled beams with an incidence angle "
          f"({int(labels.y.sum())} glass); multi-echo: {'yes' if scans and scans[0].echoes is not None else 'no'}")
    print(f"wrote {out}")
    return 0
