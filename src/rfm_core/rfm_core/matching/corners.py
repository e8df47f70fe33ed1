"""Corner correspondences of matched boxes (paper 3.3), resolving the yaw symmetry.

A gravity-aligned box is the same box after turning its frame by a quarter turn (with x and
y sizes swapped). Two detections of one object can therefore disagree on yaw by k * 90 deg
while describing the same corners in another order. :func:`relabel` gives the equivalent
box turned by k quarter turns and the permutation of its corners; the relative-pose search
tries the quarter turns that keep the footprint sizes consistent.
"""
from __future__ import annotations

import numpy as np

from rfm_core.geometry import wrap_angle

__all__ = ['relabel', 'corner_permutation', 'quarter_turn_candidates', 'quarter_turn_table', 'closest_turn']


def corner_permutation(k: int) -> np.ndarray:
    """perm (8,) with corners(relabel(box, k))[j] == corners(box)[perm[j]]."""
    k = int(k) % 4
    bottom = (np.arange(4) + k) % 4
    return np.concatenate([bottom, bottom + 4])


def relabel(boxes, k: int) -> np.ndarray:
    """The same boxes (..., 7) described with the frame turned by k quarter turns."""
    out = np.array(boxes, dtype=np.float64, copy=True)
    if int(k) % 2:
        out[..., [3, 4]] = out[..., [4, 3]]
    out[..., 6] = wrap_angle(out[..., 6] + (int(k) % 4) * np.pi / 2)
    return out


def quarter_turn_candidates(box_a, box_b, tolerance: float) -> list:
    """Quarter turns k of box_b whose footprint sizes agree with box_a's within a relative
    ``tolerance``, with the relative yaw each implies: [(k, yaw_b_k - yaw_a), ...]."""
    return quarter_turn_table(np.asarray(box_a)[None], np.asarray(box_b)[None], tolerance)[0]


def quarter_turn_table(boxes_a, boxes_b, tolerance: float) -> list:
    """:func:`quarter_turn_candidates` of each pair of rows of ``boxes_a`` and ``boxes_b``
    (n, 7), computed together: a list of n lists."""
    a = np.asarray(boxes_a, dtype=np.float64).reshape(-1, 7)
    out = [[] for _ in range(len(a))]
    for k in range(4):
        b = relabel(np.asarray(boxes_b, dtype=np.float64).reshape(-1, 7), k)
        err = np.abs(b[:, 3:5] - a[:, 3:5]) / np.maximum(np.maximum(b[:, 3:5], a[:, 3:5]), 1e-6)
        yaw = wrap_angle(b[:, 6] - a[:, 6])
        for m in np.flatnonzero(np.all(err <= tolerance, axis=1)):
            out[m].append((k, float(yaw[m])))
    return out


def closest_turn(box, yaw: float) -> int:
    """The quarter turn k of ``box`` whose relabelled yaw is closest to ``yaw``."""
    return min(range(4), key=lambda k: abs(wrap_angle(relabel(box, k)[6] - yaw)))
