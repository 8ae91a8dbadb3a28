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
   1e-4 rad^2/rad * |dyaw|, plus (2 mm)^2 and (2 mrad)^2 per second. The laser's mounting offset
   (``EstimatorConfig.laser_mount``, base frame) is applied to every scan.
2. **Correction** (``field.py``, ``matcher.py``): correlative scan-to-map matching (Olson 2009) against a
   likelihood field derived from the shared occupancy grid (distance to the nearest occupied cell, measured
   to the mean end point that fell in that cell, so walls keep sub-cell positions; Gaussian with a floor;
   rebuilt every 10 key scans on a 28 m crop; only cells within ~0.3 m of a wall are computed, the rest
   hold the floor). Two resolutions: a coarse lattice (4 cells, 4 yaw steps) over
   the whole window on a block-maximum field (an upper bound), then a fine lattice (1 cell, yaw step
   res / r90 in [0.1, 0.25] deg) with bilinear interpolation around the prior and, if its upper bound is
   higher, the best coarse candidate; all poses of a stage in one vectorized gather. The search window is
   3 sigma of the predicted covariance, clipped to [0.15, 0.5] m and [2, 10] deg.
   **Covariance from the score distribution**: pi(pose) ~ exp(beta (score - max)) over the fine lattice,
   beta = 50 / (number of end points) (the end points are correlated; calibrated with NEES); the
   covariance is its second moment plus a sub-lattice floor (0.15 step). The measurement is the vertex of
   a parabola through the peak on curved axes, the mean of pi on flat ones (e.g. along a corridor, where pi
   is elongated and the EKF keeps the prediction).
3. **Fusion** (``filter.py``): EKF (Joseph form), innovation gate chi-square(3) 21.1.
4. **Map** (key scans only): the scan is integrated into the shared :class:`~glassmap.grid.OccupancyGrid` at the corrected
   laser pose (glass mappers then run with ``update_occupancy=False`` on the same grid).

**Reported covariance**. The EKF's covariance is relative to the map built so far; the map is only as good
as the poses that built it, so each end-point cell stores the variance it was placed with (layers
``pose_var_xy``, ``pose_var_yaw``) and a match inherits the median variance of the cells it matched:
reported = EKF covariance + diag(map_xy, map_xy, map_yaw). It grows while exploring and shrinks when the
robot comes back to well-known ground.

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
