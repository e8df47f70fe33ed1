"""Depth points: a frame's cloud (``FrameObservations.cloud``) and what aligning to it needs.

:func:`depth_cloud` turns a depth image into the gravity-aligned, voxel-downsampled points
the detector sends with every frame; :class:`PointIndex` holds a cloud ready to be aligned
to (a k-d tree and the points' surface normals). The alignment itself is
:mod:`rfm_core.matching.points`.
"""
from __future__ import annotations

import numpy as np

from rfm_core.geometry import gravity_aligned_rotation

__all__ = ['depth_cloud', 'voxel_means', 'PointIndex', 'MAX_CLOUD_POINTS', 'seen_through', 'seen_through_both']

#: at most this many points per frame (a message bound; a 12 cm voxel grid of a room holds ~1,500)
MAX_CLOUD_POINTS = 20_000
_NORMAL_NEIGHBOURS = 10
_WIDE_NEIGHBOURS = 30      #: ... tried for points whose nearest ten are no surface
_MAX_CURVATURE = 0.05       #: points whose neighbourhood is not a surface (edges, noise) take no part


def depth_cloud(depth: np.ndarray, intrinsics, gravity_cam, voxel_m: float, max_range_m: float,
                columns: int = 160) -> np.ndarray:
    """(P, 3) float32 points of a depth image (metres, NaN / 0 missing) in the frame's
    gravity-aligned camera frame (:func:`rfm_core.geometry.gravity_aligned_rotation`): pixels
    on a grid about ``columns`` wide (every second of a 320-pixel image, every fourth of a
    640) within ``max_range_m``, one point per ``voxel_m`` cell (the mean of its points), at
    most :data:`MAX_CLOUD_POINTS` (a coarser grid past that)."""
    if depth is None or voxel_m <= 0:
        return np.zeros((0, 3), np.float32)
    stride = max(1, int(round(depth.shape[1] / columns)))
    z = np.asarray(depth, np.float32)[::stride, ::stride]
    v, u = np.mgrid[0:depth.shape[0]:stride, 0:depth.shape[1]:stride]
    ok = np.isfinite(z) & (z > 0.1) & (z <= max_range_m)
    z = z[ok].astype(np.float64)
    p = np.stack([(u[ok] - intrinsics.cx) / intrinsics.fx * z, (v[ok] - intrinsics.cy) / intrinsics.fy * z, z], 1)
    p = p @ gravity_aligned_rotation(gravity_cam).T
    while True:
        out = voxel_means(p, voxel_m)
        if len(out) <= MAX_CLOUD_POINTS:
            return out.astype(np.float32)
        voxel_m *= 1.5


def voxel_means(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(C, 3) float64: the mean of the ``points`` in each occupied cell of a ``voxel_m`` grid."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(p):
        return p
    cells = np.floor(p / voxel_m).astype(np.int64)
    cells -= cells.min(0)
    span = cells.max(0) + 1
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    return np.stack([np.bincount(inv, weights=p[:, k]) for k in range(3)], 1) / count[:, None]


class PointIndex:
    """A frame's cloud ready to be aligned to: a k-d tree and each point's surface normal
    (from its neighbours; points off a surface are left out)."""

    def __init__(self, cloud: np.ndarray):
        from scipy.spatial import cKDTree  # noqa: PLC0415
        self.cloud = cloud                    #: the array it was built from
        self.points = np.asarray(cloud, np.float64).reshape(-1, 3)
        self.tree = cKDTree(self.points) if len(self.points) else None
        self.normals = np.zeros_like(self.points)
        self.usable = np.zeros(len(self.points), bool)
        if len(self.points) > _NORMAL_NEIGHBOURS:
            self.normals, self.usable = self._surfaces(np.arange(len(self.points)), _NORMAL_NEIGHBOURS)
        if len(self.points) > _WIDE_NEIGHBOURS:
            # noisy depth (an active-stereo camera at 4-6 m) turns a wall into a slab a few
            # cells thick whose ten nearest points form no surface; its thirty nearest do
            # (the noise across stays, the extent along grows), while an edge's stay two surfaces
            rest = np.flatnonzero(~self.usable)
            if len(rest):
                normals, usable = self._surfaces(rest, _WIDE_NEIGHBOURS)
                self.normals[rest[usable]] = normals[usable]
                self.usable[rest[usable]] = True

    def _surfaces(self, which: np.ndarray, k: int):
        """Normals of points ``which`` from their ``k`` nearest, and whether those lie on a surface."""
        _, idx = self.tree.query(self.points[which], k=k)
        nb = self.points[idx] - self.points[idx].mean(1, keepdims=True)
        values, vectors = np.linalg.eigh(np.einsum('nki,nkj->nij', nb, nb))
        return vectors[:, :, 0], values[:, 0] <= _MAX_CURVATURE * np.maximum(values.sum(1), 1e-12)

    def __len__(self) -> int:
        return int(self.usable.sum())


def seen_through(cloud_a: np.ndarray, rotation_a: np.ndarray, cloud_b: np.ndarray, t_a_b: np.ndarray,
                 bin_rad: float = 0.03, margin_m: float = 0.15, margin_ratio: float = 0.05) -> tuple:
    """(points, contradicted): of frame b's points moved into frame a by ``t_a_b`` (4x4; both
    clouds gravity-aligned, ``rotation_a`` a's aligned-from-camera rotation), those that fall
    on rays of a's camera where a measured a surface (``bin_rad`` wide), and of them those
    in front of that surface by more than ``margin_m`` + ``margin_ratio`` of its distance:
    in space camera a saw through. Two views placed right contradict little (depth noise,
    thin objects); a look-alike placement puts one room's surfaces across the other's view."""
    def rays(points):
        p = np.asarray(points, np.float64) @ rotation_a           # aligned -> a's camera (R.T p)
        p = p[p[:, 2] > 0.1]
        return np.floor(p[:, :2] / p[:, 2:3] / bin_rad).astype(np.int64), p[:, 2]
    if not len(cloud_a) or not len(cloud_b):
        return 0, 0
    key_a, z_a = rays(cloud_a)
    moved = np.asarray(cloud_b, np.float64) @ t_a_b[:3, :3].T + t_a_b[:3, 3]
    key_b, z_b = rays(moved)
    if not len(key_a) or not len(key_b):
        return 0, 0
    code_a = key_a[:, 0] * 1_000_003 + key_a[:, 1]
    code_b = key_b[:, 0] * 1_000_003 + key_b[:, 1]
    order = np.lexsort((z_a, code_a))                             # per ray, nearest surface first
    codes, first = np.unique(code_a[order], return_index=True)
    nearest = z_a[order][first]
    at = np.searchsorted(codes, code_b)
    at[at >= len(codes)] = 0
    hit = codes[at] == code_b
    surface = nearest[at[hit]]
    return int(hit.sum()), int(np.count_nonzero(z_b[hit] < surface - (margin_m + margin_ratio * surface)))


def seen_through_both(cloud_a: np.ndarray, rotation_a: np.ndarray, cloud_b: np.ndarray, rotation_b: np.ndarray,
                      t_a_b: np.ndarray) -> tuple:
    """:func:`seen_through` both ways, summed: (points, contradicted) of b's points in a's
    view and a's in b's (``t_a_b`` 4x4 between the two gravity-aligned frames)."""
    n1, v1 = seen_through(cloud_a, rotation_a, cloud_b, t_a_b)
    n2, v2 = seen_through(cloud_b, rotation_b, cloud_a, np.linalg.inv(t_a_b))
    return n1 + n2, v1 + v2
