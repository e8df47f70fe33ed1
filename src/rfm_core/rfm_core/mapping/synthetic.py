"""Synthetic view graphs with known poses, for tests and benchmarks of the averaging."""
from __future__ import annotations

import numpy as np

from rfm_core.geometry import Pose4, wrap_angle

__all__ = ['synthetic_view_graph']


def synthetic_view_graph(n: int, seed: int = 0, neighbours: int = 3, loops: float = 0.2,
                         yaw_noise_deg: float = 0.0, translation_noise_m: float = 0.0,
                         outliers: float = 0.0, step_m: float = 0.3):
    """A camera walking through a room: ``n`` keyframes, edges to the next ``neighbours``
    keyframes plus ``loops`` x n random edges between keyframes near each other in space.

    Returns (truth {id: Pose4 T_k_map}, edges [(s, t, Pose4 T_s_t, weight)], outlier flags).
    """
    rng = np.random.default_rng(seed)
    yaw = wrap_angle(np.cumsum(rng.normal(0, 0.3, n)) + rng.uniform(-np.pi, np.pi))
    heading = np.cumsum(rng.normal(0, 0.4, n))
    steps = np.stack([np.cos(heading), np.sin(heading), rng.normal(0, 0.05, n)], 1) * step_m
    centres = np.cumsum(steps, 0)
    centres[:, 2] = 1.5 + 0.1 * np.sin(np.arange(n) / 7)
    truth = {k: Pose4.from_centre(float(yaw[k]), centres[k]) for k in range(n)}
    pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + neighbours + 1))}
    for _ in range(int(loops * n)):
        i = int(rng.integers(n))
        d = np.linalg.norm(centres - centres[i], axis=1)
        near = np.flatnonzero((d < 1.5) & (np.abs(np.arange(n) - i) > neighbours))
        if len(near):
            j = int(rng.choice(near))
            pairs.add((min(i, j), max(i, j)))
    edges, flags = [], []
    for i, j in sorted(pairs):
        rel = truth[i] @ truth[j].inverse()                  # T_i_j
        bad = rng.random() < outliers
        if bad:
            rel = Pose4(float(rng.uniform(-np.pi, np.pi)), rel.t + rng.normal(0, 1.0, 3))
        else:
            rel = Pose4(rel.yaw + np.radians(yaw_noise_deg) * rng.normal(),
                        rel.t + translation_noise_m * rng.normal(size=3))
        edges.append((i, j, rel, 1.0))
        flags.append(bad)
    return truth, edges, np.array(flags)
