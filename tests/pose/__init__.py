"""Tests of the pose estimator (glassmap.pose)."""
