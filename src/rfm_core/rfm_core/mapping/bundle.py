"""Partial bundle adjustment of object tracks (paper 3.6 and appendix).

Poses stay fixed; each track's box (centre, size, yaw) is optimised so that its corners,
projected into every keyframe observing it, land on the projected corners of that
keyframe's detection — the paper's reprojection cost, normalised by the image size. The
corner correspondence (track corner n <-> detection corner m) resolves the box's yaw
symmetry geometrically: the quarter turn of the lifted detection closest in yaw to the
track's box. Sizes are optimised in log space (they stay positive), a weak prior keeps a
box seen from a narrow baseline near its start, and a robust (Huber) loss discounts
occluded or truncated detections.

This is what fixes monocular depth errors: a box scaled along the viewing ray projects to
the same image, so one view cannot tell its distance but several views can.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from rfm_core.geometry import box_corners, wrap_angle
from rfm_core.matching.corners import closest_turn, corner_permutation
from rfm_core.settings import constant, setting

__all__ = ['BundleConfig', 'refine_tracks']


@dataclass(frozen=True)
class BundleConfig:
    max_evaluations: int = constant(60, 'Cost evaluations per track', lo=1, hi=100000)
    max_seconds: float = setting(2.0, 'Time per refinement; remaining tracks keep their boxes (s)',
                                 lo=0.01, hi=3600.0)
    min_observations: int = constant(2, 'Refine tracks seen in at least this many keyframes', lo=1, hi=1000)
    loss_scale: float = constant(0.01, 'Huber scale of the normalised reprojection error', lo=1e-4, hi=1.0)
    prior_weight: float = constant(0.02, 'Weak pull to the starting box (m and log-size)', lo=0.0, hi=100.0)
    min_depth_m: float = constant(0.1, 'Corners nearer the camera than this are ignored (m)', lo=0.0, hi=10.0)


def _params(box):
    return np.r_[box[:3], np.log(np.maximum(box[3:6], 1e-3)), box[6]]


def _box(x):
    return np.r_[x[:3], np.exp(x[3:6]), x[6]]


def _project(points_cam, k):
    z = points_cam[..., 2]
    return np.stack([k[0] * points_cam[..., 0] / z + k[2], k[1] * points_cam[..., 1] / z + k[3]], -1)


def refine_tracks(tracks, keyframes: dict, poses: dict, config: BundleConfig | None = None) -> list:
    """Tracks with their boxes refined against their observations (new Track objects)."""
    cfg = config or BundleConfig()
    start = time.perf_counter()
    out = []
    for track in tracks:
        if (track.num_observations < cfg.min_observations
                or time.perf_counter() - start > cfg.max_seconds):
            out.append(track)
            continue
        box = _refine_one(track, keyframes, poses, cfg)
        out.append(track if box is None else replace(track, box=box))
    return out


def _refine_one(track, keyframes, poses, cfg):
    views = []
    for (k, det), lifted in zip(track.observations, track.boxes):
        obs = keyframes.get(int(k))
        pose = poses.get(int(k))
        if obs is None or pose is None or obs.intrinsics is None:
            continue
        intr = obs.intrinsics
        r_cam_aligned = obs.rotation_aligned_from_camera.T
        # the quarter turn of the detection closest in yaw to the track's box
        q = closest_turn(lifted, track.box[6])
        perm = corner_permutation(q)
        corners_cam = box_corners(obs.map_boxes[int(det)])[perm] @ r_cam_aligned.T
        ok = corners_cam[:, 2] > cfg.min_depth_m
        if np.count_nonzero(ok) < 4:
            continue
        k_vec = np.array([intr.fx, intr.fy, intr.cx, intr.cy])
        scale = np.array([intr.width, intr.height], float)
        views.append((pose, r_cam_aligned, k_vec, scale, ok, _project(corners_cam, k_vec)))
    if len(views) < cfg.min_observations:
        return None
    x0 = _params(track.box)

    def residuals(x):
        corners_map = box_corners(_box(x))
        res = []
        for pose, r, k_vec, scale, ok, uv in views:
            cam = pose.transform_points(corners_map) @ r.T
            z = np.maximum(cam[:, 2], cfg.min_depth_m)
            proj = _project(np.c_[cam[:, :2], z], k_vec)
            res.append(((proj - uv) / scale)[ok].ravel())
        prior = cfg.prior_weight * np.r_[x[:3] - x0[:3], x[3:6] - x0[3:6]]
        return np.concatenate(res + [prior])

    try:
        sol = least_squares(residuals, x0, loss='huber', f_scale=cfg.loss_scale, max_nfev=cfg.max_evaluations)
    except (ValueError, np.linalg.LinAlgError):
        return None
    box = _box(sol.x)
    if not np.all(np.isfinite(box)) or np.any(box[3:6] > 20.0):
        return None
    box[6] = wrap_angle(box[6])
    return box
