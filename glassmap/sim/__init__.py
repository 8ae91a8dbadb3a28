"""Simulator: a 2D world of segments with materials, a laser with glass physics, a Pioneer 3-DX with noisy
odometry, ground-truth blueprints, datasets and renderings. See docs/simulator.md."""
