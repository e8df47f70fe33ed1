"""Relative poses refined on the two frames' depth points (not in the paper).

A depth detector's boxes fit the part of each object in view: where the image border cuts
an object, or another hides part of it, the box's centre moves by a good fraction of the
object from one view to the next. The depth points themselves do not move: where two
views see the same surface they see it at the same place. So a relative pose the boxes
found (which already has the right matches and is near the truth) is refined by aligning
the two frames' depth points, as RGB-D odometry does: point-to-plane ICP in 4-DoF (yaw
about gravity and translation; both frames are gravity-aligned), each point robustly
weighted. What the points do not determine (a view of
the floor and one wall leaves a direction free) stays as the boxes put it, and the result is
kept where enough of the points lie on the other frame's surfaces (however many lay there at
the boxes' pose: on noisy depth a fit closer to the truth often holds fewer).

The clouds themselves: :mod:`rfm_core.clouds`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.clouds import PointIndex
from rfm_core.geometry import Pose4

__all__ = ['PointAlignment', 'align_points']

_ROBUST_M = 0.02            #: Cauchy scale of the point-to-plane residuals (m)
_MAX_MOVING = 500           #: points of the moving cloud aligned (an even subsample: bounded cost)


@dataclass(frozen=True)
class PointAlignment:
    pose: Pose4            #: the refined pose
    overlap: float         #: share of the moved points within ``match_m`` of a surface, refined
    overlap_before: float  #: ... at the starting pose
    residual_m: float      #: median |point-to-plane| distance of those points, refined
    free: int              #: directions (yaw, x, y, z; with ``tilt`` the two tilts too) the points left free
    tilt_deg: float = 0.0  #: with ``tilt``: the tilt between the two frames' gravity the points found (deg)


def _pairs(index: PointIndex, moved: np.ndarray, max_m: float):
    """(usable, nearest index, distance) of each moved point's nearest surface point within ``max_m``."""
    dist, j = index.tree.query(moved, distance_upper_bound=max_m)
    ok = np.isfinite(dist)
    ok[ok] &= index.usable[j[ok]]
    return ok, j, dist


def _overlap(index: PointIndex, moved: np.ndarray, match_m: float) -> tuple[float, float]:
    ok, j, _ = _pairs(index, moved, match_m)
    if not ok.any():
        return 0.0, float('inf')
    r = np.abs(np.sum(index.normals[j[ok]] * (moved[ok] - index.points[j[ok]]), axis=1))
    return float(np.mean(ok)), float(np.median(r))


def _rotation(w: np.ndarray) -> np.ndarray:
    """The rotation by rotation vector ``w`` (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _rotation_vector(r: np.ndarray) -> np.ndarray:
    """The rotation vector of rotation matrix ``r`` (small angles: exact enough to 180 deg)."""
    angle = float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return v * (0.5 if angle < 1e-9 else angle / (2.0 * np.sin(angle)))


def align_points(pose: Pose4, moving: np.ndarray, fixed: PointIndex, search_m: float = 0.25,
                 match_m: float = 0.05, iterations: int = 5, min_points: int = 50,
                 tilt: bool = False) -> PointAlignment | None:
    """Refine ``pose`` (maps ``moving``'s frame into ``fixed``'s) by 4-DoF point-to-plane ICP:
    two steps with correspondences within ``search_m``, two within half that, then at most
    ``iterations`` within ``match_m`` (fewer once a step moves less than 1 mm / 0.03 deg);
    Cauchy-weighted residuals; Levenberg-damped steps; at most 500 moving points (an even
    subsample). Directions the points do not constrain (the smallest eigenvalues of their
    information, with the rotations at a 1 m lever arm, below 1% of the largest) keep
    ``pose``'s value. None with fewer than ``min_points`` correspondences.

    ``tilt``: the two frames' gravity may disagree by a degree or two (each frame's gravity is
    the IMU filter's estimate), which at a few metres moves points by more than ``match_m``;
    the alignment then also turns the moving cloud about the two horizontal axes through its
    camera (6-DoF), and returns the yaw and translation (the camera's position) of that
    alignment, its overlap, and the tilt it found."""
    moving = np.asarray(moving, np.float64).reshape(-1, 3)
    if len(moving) > _MAX_MOVING:
        moving = moving[np.linspace(0, len(moving) - 1, _MAX_MOVING).astype(int)]
    if len(moving) < min_points or fixed.tree is None or len(fixed) < min_points:
        return None
    rot, t = pose.rotation, np.asarray(pose.t, float)
    axes = slice(0, 3) if tilt else slice(2, 3)            # rotations about x, y, z or about z only
    n_rot = 3 if tilt else 1
    damping = np.diag([1.0] * n_rot + [0.1] * 3)
    levels = [search_m, max(search_m / 2, match_m), match_m]
    info, before = None, None
    for level, max_m in enumerate(levels):
        for _ in range(iterations if level == len(levels) - 1 else 2):
            q = moving @ rot.T + t
            ok, j, dist = _pairs(fixed, q, max_m)
            if before is None:                                  # the starting pose's overlap
                before = float(np.mean(ok & (dist <= match_m)))
            if ok.sum() < min_points:
                return None
            q, n, p = q[ok], fixed.normals[j[ok]], fixed.points[j[ok]]
            r = np.sum(n * (q - p), axis=1)
            jac = np.c_[np.cross(q, n)[:, axes], n]         # d r / d(rotation about the fixed axes, t)
            w = 1.0 / (1.0 + (r / _ROBUST_M) ** 2)
            info = (jac * w[:, None]).T @ jac
            step = -np.linalg.solve(info + 1e-3 * w.sum() * damping, (jac * w[:, None]).T @ r)
            turn = _rotation(np.r_[np.zeros(3 - n_rot), step[:n_rot]])     # the step, in the fixed frame
            rot, t = turn @ rot, turn @ t + step[n_rot:]
            if np.linalg.norm(step[:n_rot]) < 5e-4 and np.linalg.norm(step[n_rot:]) < 1e-3:
                break
    # what the points leave free stays as the start put it (with tilt: each rotation weighed at the
    # points' lever arm, so that a turn and a shift compare as the displacement they cause)
    delta = np.r_[_rotation_vector(rot @ pose.rotation.T)[axes], t - pose.t]
    if tilt:
        arm = np.r_[[float(np.sqrt(np.mean(np.sum(q ** 2, axis=1))))] * n_rot, [1.0] * 3]
        info = info / np.outer(arm, arm)
        delta = delta * arm
    values, vectors = np.linalg.eigh(info)
    free = values < 1e-2 * max(values.max(), 1e-12)
    if free.any():
        delta -= vectors[:, free] @ (vectors[:, free].T @ delta)
    if tilt:
        delta = delta / arm
    rot = _rotation(np.r_[np.zeros(3 - n_rot), delta[:n_rot]]) @ pose.rotation
    t = pose.t + delta[n_rot:]
    overlap, residual = _overlap(fixed, moving @ rot.T + t, match_m)
    yaw = float(np.arctan2(rot[1, 0] - rot[0, 1], rot[0, 0] + rot[1, 1]))   # the nearest turn about z
    tilt_deg = float(np.degrees(np.arccos(np.clip(rot[2, 2], -1.0, 1.0))))
    return PointAlignment(Pose4(yaw, t), overlap, before, residual, int(free.sum()), tilt_deg)
