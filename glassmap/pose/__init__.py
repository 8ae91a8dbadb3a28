"""Online pose + covariance estimation of the base in the map frame (metres, radians), one estimate per laser
scan: odometry prediction, correlative scan-to-map matching, EKF fusion. Design: docs/pose.md."""

from glassmap.pose.estimator import EstimatorConfig, EstimatorStats, PoseEstimator
from glassmap.pose.field import FieldParams, LikelihoodField
from glassmap.pose.matcher import CorrelativeMatcher, MatcherConfig, MatchResult
from glassmap.pose.motion import MotionNoise, OdometryBuffer

__all__ = ["PoseEstimator", "EstimatorConfig", "EstimatorStats", "MotionNoise", "OdometryBuffer",
           "CorrelativeMatcher", "MatcherConfig", "MatchResult", "FieldParams", "LikelihoodField"]
