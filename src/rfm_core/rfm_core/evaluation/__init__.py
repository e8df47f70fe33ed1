"""Evaluation as in the paper: AP/AR at 3D IoU 0.15 / 0.25; ATE / ARE / registration."""
