"""Synthetic indoor scenes: rooms, RGB-D rendering, camera trajectories, ground truth."""
