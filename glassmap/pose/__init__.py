"""Online pose + covariance estimation of the base in the map frame, one estimate per laser scan.

Pipeline per scan (:class:`PoseEstimator`). Every scan gets step 1 (a pose + covariance at its stamp);
steps 2-4 run only on **key scans** (motion filter, as in GMapping / Cartographer): the first scan, and any
scan whose predicted pose has moved >= 5 cm or turned >= 2 deg since the last key scan, or that comes 20
scans after it (``EstimatorConfig.keyframe_distance / keyframe_angle / keyframe_max_scans``; 0 / 0 gives
the old every-scan behaviour). Between key scans the pose follows odometry from the last corrected pose
(over at most a few cm the odometry error is far below a cell), and matching the same view again and
again would only re-use the same map error (measured by ``glassmap pose eval``: ATE is lower with the
filter than without).

1. **Prediction** (``motion.py``): wheel odometry is buffered (any rate) and interpolated to the scan's
   time (extrapolated with the last velocity for at most 0.25 s); the increment since the previous scan is
   composed onto the state. Motion noise (:class:`MotionNoise`): per increment of length d and turn
   |dyaw| over dt, diagonal in the direction of travel: along-track (2 % of d)^2 + 1.5e-5 m^2/m * d,
   lateral (1 % of d)^2 + 1.5e-5 * d, yaw (3 % of |dyaw|)^2 + (0.01 rad/m * d)^2 + 4e-4 rad^2/m * d +
   1e-4 rad^2/rad * |dyaw|, plus (2 mm)^2 and (2 mrad)^2 per second. A scan after the newest odometry
   message is extrapolated with that message's velocity, whose error (0.02 m/s, 0.1 rad/s: measured on the
   simulated P3-DX, 0.018 m/s and 0.09-0.096 rad/s) is added to the reported covariance for that scan only
   (the next message replaces the extrapolation). The laser's mounting offset
   (``EstimatorConfig.laser_mount``, base frame) is applied to every scan.
2. **Correction** (``field.py``, ``matcher.py``): correlative scan-to-map matching (Olson 2009) against a
   likelihood field derived from the shared occupancy grid: per cell near a wall, the vector to the wall
   point of the nearest occupied cell, that point being the mean of the end points that fell in the 3 x 3
   cells around it (sub-cell walls that do not lean away from where they were seen from), measured along
   the wall's normal where the 5 x 5 neighbourhood is a straight wall (no saw-tooth along walls); the
   likelihood is a Gaussian of its length (sigma_hit 3 cm) with a floor; rebuilt every 10 key scans on a
   28 m crop (in a worker thread), only cells within ~0.2 m of a wall are computed. End points: beams
   thinned by index (a stride from the neighbouring beams' ranges, about one per 8 cm of arc), never by
   which beam falls first in a voxel (that keeps beams by the sign of their noise: a yaw bias per match).
   Two resolutions: a coarse lattice (4 cells, 4 yaw steps) over
   the whole window on a block-maximum field (an upper bound), then a fine lattice (1 cell, yaw step
   res / r90 in [0.1, 0.25] deg) around the prior, where the vector field is interpolated bilinearly
   (exact near a straight wall, so points are not pulled towards cell centres) and, if its upper bound is
   higher, the best coarse candidate; all poses of a stage in one vectorized gather. The search window is
   3 sigma of the predicted covariance, clipped to [0.15, 0.5] m and [2, 10] deg.
   **Covariance from the score distribution**: pi(pose) ~ exp(beta (score - max)), beta =
   min(1, 120 / number of end points) (the end points are correlated). By the law of total variance its
   covariance is the second moment of pi over the fine lattice (the spread between cells: along a
   corridor, between near-equal peaks) plus the spread inside the peak's cell, the Gaussian of the score's
   curvature there ((beta H)^-1, H by central differences at the scale of that spread; each axis at most
   a uniform spread over the cell). Key-scan matches are sharper than the 5 cm lattice, so the lattice
   alone would report ~0; in a box with walls on cell centres the result is sigma_hit / sqrt(beta N) with
   N the points on the walls facing each axis, within about 5 % (``tests/pose/test_matcher.py``). The
   measurement is the vertex of a parabola through the peak on curved axes, the mean of pi on flat ones
   (e.g. along a corridor, where pi is elongated and the EKF keeps the prediction).
   With ``EstimatorConfig.deskew`` (off by default: the simulator does not model the sweep) a key scan is
   first de-skewed with the odometry over its ~19 ms sweep (:func:`glassmap.pose.motion.deskew`).
3. **Fusion** (``filter.py``): EKF (Joseph form), innovation gate chi-square(3) 21.1.
4. **Map** (key scans only): the scan is integrated into the shared :class:`~glassmap.grid.OccupancyGrid` at the corrected
   laser pose (glass mappers then run with ``update_occupancy=False`` on the same grid).

**Reported covariance** = relative part + map part.

- Relative to the map built so far: the EKF's covariance, every match fused as independent (its error
  relative to the map is mostly its own scan's; measured per axis on seed 0: office 2.35 mm against 2.20
  mm reported, room 1.61 / 2.12, glass-corridor 2.62 / 2.31). ``EstimatorConfig.correlated_matches``
  instead reports a Schmidt-style "consider" covariance (``PoseEKF.actual_cov``) that counts the error two
  consecutive matches share through the wall blocks (the 3 x 3 cells the field averages into one wall
  point) they both use; it made room too wide (mean NEES 1.3-1.6).
- The map part: each end-point cell keeps the error model of its best placement (the one that placed the
  cell itself most precisely): a shift (variance per axis) and a rotation about a pivot (layers
  ``pose_var_shift``, ``pose_var_yaw``, ``pose_var_pivot_x/_y``). A robot at X matched against it inherits
  the shift plus the rotation's lever arm perp(X - pivot), correlated with yaw. The matched cells share
  their error (a chain of matches placed them), so the region's model is the mean of their standard
  deviations, one rotation about their weighted pivot (``map_cov``, ``map_region``).
- New cells inherit the matched region's rotation and pivot, plus the filter's relative error. A wall
  extended from a matched wall keeps its direction error, so along a corridor the sideways uncertainty
  grows linearly with the distance from where that error came from. On ``office``, glass on one side
  gave a persistent 1 mm per metre of sideways drift; with a pivot reset at every placement the model
  grew like a random walk and reported less than half of it (6 mm against 14 mm on seed 3).
- The map frame is defined by the first pose, so the initial covariance is ~0 (0.1 mm, 0.1 mrad). An
  initial yaw variance rotates the whole map about the start: 1 mrad reported 2 cm at the far end of
  the office.

**Map-building feedback** (why the field and the point selection are built as above). Every scan is
matched against a map built from earlier matched poses, so any bias of a single match, however small,
is written into the map and accumulates: measured on ``office`` with perfect odometry, first-beam-per-voxel
point selection, per-cell wall means and an interpolated likelihood drifted 8 cm along and across the
corridor over 33 m, although the same matcher against a map built from the true poses had no bias.

**Registration sigma** (:meth:`PoseEstimator.registration_sigma`), per beam of range r:
sigma(r)^2 = sigma_xy^2 + (r sigma_theta)^2 + sigma_r(r)^2 with sigma_xy the square root of the larger
eigenvalue of the laser position covariance (the worst direction: a corridor's long axis counts, and the
mount's lever arm is included), sigma_theta the yaw standard deviation, and sigma_r = 10 mm + 1 mm/m the
Hokuyo's range noise. A position error moves every end point rigidly, a yaw error moves it sideways by r
dtheta; treated as independent (the xy-yaw correlation is small after matching).

**Glass**. A pane returns the beam only near normal incidence; at larger angles the beam passes and ranges
what is behind, so the pane is in some scans and not in others and the occupancy grid holds it partly
(pass-through beams clear its cells). Matching stays robust because every end point's likelihood has a
floor (a point on a pane the map does not hold costs a constant, it does not drag the pose), but the
inconsistent pane cells add yaw noise. ``EstimatorConfig.glass_weighting`` down-weights beams ending on
cells the ``"glass"`` layer of the grid believes are glass (weight 1 at p = 0.5 falling to 0.1 at p = 1),
``protect_glass`` (or ``PoseEstimator.protect_mask_fn``, e.g. the glass mapper's) keeps such cells from
being cleared. ``glassmap pose eval --glass-weighting oracle`` measures the effect with the true glass
cells.
"""

from glassmap.pose.estimator import EstimatorConfig, EstimatorStats, PoseEstimator
from glassmap.pose.field import FieldParams, LikelihoodField
from glassmap.pose.matcher import CorrelativeMatcher, MatcherConfig, MatchResult
from glassmap.pose.motion import MotionNoise, OdometryBuffer

__all__ = ["PoseEstimator", "EstimatorConfig", "EstimatorStats", "MotionNoise", "OdometryBuffer",
           "CorrelativeMatcher", "MatcherConfig", "MatchResult", "FieldParams", "LikelihoodField"]
