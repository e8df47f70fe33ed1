"""How far off a pose may be: covariances of the keyframes' poses and of every localized frame.

Pose averaging (:mod:`rfm_core.mapping.averaging`) weighs each relative pose by the objects
that verified it (a depth-point edge and the gyroscope's yaw by their own weights, in the same
unit). The same weights are the measurements' information: a relative pose of weight w has
standard deviations ``pose_sigma_deg / sqrt(w)`` in yaw and ``pose_sigma_m / sqrt(w)`` per
axis of its translation (:class:`~rfm_core.mapping.averaging.AveragingConfig`; both
calibrated on tuning rooms against their ground truth, docs/design-notes.md). Linearized at
the solution, with the anchor keyframe holding the map frame:

- yaw stage: H_yaw = sum_e w_e / s_yaw^2 (u_s - u_t)(u_s - u_t)^T over the kept edges;
- translation stage, yaws given: H_c = sum_e w_e / s_t^2 (u_t - u_s)(u_t - u_s)^T per axis,
  and the centres move with the yaws through each edge's measured offset Rz(theta_s)^T t_st:
  dc/dtheta = H_c^-1 B, B = sum_e w_e / s_t^2 (u_t - u_s) d(Rz(theta_s)^T t_st)/dtheta_s.

A keyframe's covariance over (theta, centre) is then [[S_kk, (G_k S_k)^T], [G_k S_k,
H_c^-1_kk I + G_k S G_k^T]] with S = H_yaw^-1, G = dc/dtheta. A frame's adds its pose
relative to its keyframe (weighed by the objects that placed it, or as a depth-point edge),
composed to first order. Where the solution's residuals say the measurements are noisier
than stated (their chi-square over the redundancy, pooled with ``pose_sigma_prior_dof``
observations of the stated noise), each stage grows by that factor, never shrinks. The map
frame's roll and pitch are the gravity estimate's (``tilt_sigma_deg``). The covariance says
how far a pose may be off when its measurements are right; a wrong relative pose that
nothing contradicted is not in it.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from rfm_core.geometry import Pose4

__all__ = ['KeyframeCovariances', 'relative_covariance', 'track_weight', 'tracked_covariance', 'frame_covariance',
           'ros_pose_covariance']

_EPS = 1e-12


def _variance_factor(chi2: float, redundancy: int, prior_dof: float) -> float:
    """How much noisier the measurements are than stated, estimated from the solution's
    normalized residuals (``chi2`` over ``redundancy`` degrees of freedom) pooled with
    ``prior_dof`` observations of exactly the stated noise; never below 1 (the stated noise
    is the floor)."""
    return max(1.0, (prior_dof + chi2) / (prior_dof + max(redundancy, 0)))


def relative_covariance(weight: float, sigma_yaw: float, sigma_t: float) -> np.ndarray:
    """(4, 4) covariance over (yaw, x, y, z) of a relative pose of averaging ``weight``
    (0: exact, a keyframe relative to itself); sigmas in rad and m."""
    if weight <= 0:
        return np.zeros((4, 4))
    return np.diag([sigma_yaw ** 2, sigma_t ** 2, sigma_t ** 2, sigma_t ** 2]) / weight


def track_weight(num_inliers: int, is_keyframe: bool, points_edge_weight: float) -> float:
    """The averaging weight of a frame's pose relative to its keyframe: the objects that
    verified it, a depth-point edge's where none did, 0 (exact) for the keyframe itself."""
    return 0.0 if is_keyframe else float(num_inliers or points_edge_weight)


def tracked_covariance(num_inliers: int, is_keyframe: bool, averaging) -> np.ndarray:
    """(16,) row-major covariance over (x, y, z, yaw) of a tracked frame's pose relative to
    its keyframe (rfm_msgs/TrackedFrame ``covariance``), as its measurement states it (the
    averaging's noise constants, ``averaging``: an AveragingConfig); the mapper grows it by
    the map's variance factors where the residuals say so."""
    cov = relative_covariance(track_weight(num_inliers, is_keyframe, averaging.points_edge_weight),
                              np.radians(averaging.pose_sigma_deg), averaging.pose_sigma_m)
    order = [1, 2, 3, 0]                        # (yaw, x, y, z) -> (x, y, z, yaw)
    return cov[np.ix_(order, order)].reshape(16)


class KeyframeCovariances:
    """The keyframes' pose covariances over (theta_k, c_k) (see the module), computed on
    demand for one solution of the averaging.

    ``theta`` (n,), ``centres`` (n, 3): the solution (NaN outside it); edges ``src``, ``dst``,
    ``trans`` (T_src_dst's translation), ``weight``, ``yaw_only``, and their residuals under the
    solution ``residual_yaw`` (rad, wrapped) and ``residual_t`` (E, 3); only ``used`` edges count;
    ``anchor``: the index that holds the map frame; ``prior_dof``: see :func:`_variance_factor`;
    ``positions``: {keyframe id: index} (called with an id), or None (called with an index).

    Where the solution's residuals say the measurements are noisier than stated, each stage's
    covariance grows by that factor (:attr:`yaw_factor`, :attr:`translation_factor`), and so
    should the frames' relative poses (:meth:`relative`)."""

    def __init__(self, theta, centres, src, dst, trans, weight, yaw_only, used, residual_yaw, residual_t,
                 anchor: int, sigma_yaw: float, sigma_t: float, prior_dof: float = 10.0,
                 positions: dict | None = None):
        self.positions = positions
        self.sigma_yaw, self.sigma_t = sigma_yaw, sigma_t
        self.yaw_factor = self.translation_factor = 1.0
        n = len(theta)
        reg = np.isfinite(theta) & np.all(np.isfinite(centres), axis=1)
        self.registered = reg
        free = reg.copy()
        if 0 <= anchor < n:
            free[anchor] = False
        self.index = -np.ones(n, np.int64)
        self.index[free] = np.arange(np.count_nonzero(free))
        m = int(np.count_nonzero(free))
        self.m = m
        self._cache: dict = {}
        self._lu_yaw = self._lu_c = None
        if m == 0:
            return
        use = np.asarray(used, bool) & reg[src] & reg[dst]
        s, d, w = src[use], dst[use], weight[use]
        self.yaw_factor = _variance_factor(np.sum(w * residual_yaw[use] ** 2) / sigma_yaw ** 2, len(s) - m,
                                           prior_dof)
        self._lu_yaw = self._factor(self._laplacian(s, d, w / (self.yaw_factor * sigma_yaw ** 2)))
        full = ~np.asarray(yaw_only, bool)[use]
        s, d, w, t, r_t = s[full], d[full], w[full], trans[use][full], residual_t[use][full]
        self.translation_factor = _variance_factor(np.sum(w * np.sum(r_t ** 2, 1)) / sigma_t ** 2,
                                                   3 * (len(s) - m), prior_dof)
        info = w / (self.translation_factor * sigma_t ** 2)
        self._lu_c = self._factor(self._laplacian(s, d, info))
        # B (m, 3, m): how the right-hand side of the centres' normal equations moves with theta_s
        c, si = np.cos(theta[s]), np.sin(theta[s])
        dmeas = np.stack([-si * t[:, 0] + c * t[:, 1], -c * t[:, 0] - si * t[:, 1], np.zeros(len(s))], 1)
        a_s, a_d = self.index[s], self.index[d]
        rows, cols, vals = [], [], []
        for node, sign in ((a_d, 1.0), (a_s, -1.0)):
            ok = (node >= 0) & (a_s >= 0)
            for axis in range(3):
                rows.append(node[ok] * 3 + axis)
                cols.append(a_s[ok])
                vals.append(sign * info[ok] * dmeas[ok, axis])
        self._b = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(3 * m, m))

    def _laplacian(self, s, d, info):
        """sum_e info_e (u_s - u_d)(u_s - u_d)^T over the free nodes (the anchor's row and column dropped)."""
        a, b = self.index[s], self.index[d]
        rows, cols, vals = [], [], []
        for x, y, sign in ((a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)):
            ok = (x >= 0) & (y >= 0)
            rows.append(x[ok])
            cols.append(y[ok])
            vals.append(sign * info[ok])
        h = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(self.m, self.m))
        return h + sp.identity(self.m, format='csc') * _EPS

    @staticmethod
    def _factor(h):
        return splu(sp.csc_matrix(h))

    def relative(self, weight: float) -> np.ndarray:
        """(4, 4) covariance over (yaw, t) of a relative pose of averaging ``weight`` (0: exact),
        grown by the solution's variance factors."""
        return relative_covariance(weight, self.sigma_yaw * np.sqrt(self.yaw_factor),
                                   self.sigma_t * np.sqrt(self.translation_factor))

    def __call__(self, k: int) -> np.ndarray | None:
        """(4, 4) over (theta_k, c_k) of keyframe ``k``; zeros for the anchor, None outside the
        solution."""
        if self.positions is not None:
            k = self.positions.get(k, -1)
        if not (0 <= k < len(self.registered)) or not self.registered[k]:
            return None
        if k in self._cache:
            return self._cache[k]
        out = np.zeros((4, 4))
        i = self.index[k]
        if i >= 0:
            e = np.zeros(self.m)
            e[i] = 1.0
            col_yaw = self._lu_yaw.solve(e)                  # S e_k
            col_c = self._lu_c.solve(e)                      # H_c^-1 e_k
            rows = np.stack([self._b[axis::3].T @ col_c for axis in range(3)])      # G_k (3, m), per axis
            s_g = np.stack([self._lu_yaw.solve(r) for r in rows])                   # S G_k^T, (3, m)
            out[0, 0] = col_yaw[i]
            cross = rows @ col_yaw                                                  # G_k S e_k
            out[0, 1:] = out[1:, 0] = cross
            out[1:, 1:] = np.eye(3) * col_c[i] + rows @ s_g.T
        self._cache[k] = out
        return out


def frame_covariance(theta_k: float, cov_k: np.ndarray, rel: Pose4, cov_rel: np.ndarray) -> np.ndarray:
    """(4, 4) over (theta_f, c_f) of a frame placed at ``rel`` (T_keyframe_frame, covariance
    ``cov_rel`` over its (yaw, t)) from a keyframe at (``theta_k``, covariance ``cov_k``):
    theta_f = theta_k - yaw_rel, c_f = c_k + Rz(theta_k)^T t_rel, to first order."""
    c, s = np.cos(theta_k), np.sin(theta_k)
    rot_t = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])          # Rz(theta_k)^T
    d_rot = np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])        # d Rz(theta)^T / d theta
    t = np.asarray(rel.t, float)
    j_k = np.eye(4)
    j_k[1:, 0] = d_rot @ t
    j_r = np.zeros((4, 4))
    j_r[0, 0] = -1.0
    j_r[1:, 1:] = rot_t
    return j_k @ cov_k @ j_k.T + j_r @ cov_rel @ j_r.T


def ros_pose_covariance(cov: np.ndarray, tilt_sigma: float) -> np.ndarray:
    """(36,) row-major geometry_msgs/PoseWithCovariance covariance (x, y, z, then rotations
    about the map's x, y and z axes) of a camera pose whose (theta, centre) covariance is
    ``cov``: the heading about z is -theta; roll and pitch from gravity (``tilt_sigma`` rad)."""
    out = np.zeros((6, 6))
    out[:3, :3] = cov[1:, 1:]
    out[5, 5] = cov[0, 0]
    out[:3, 5] = out[5, :3] = -cov[1:, 0]
    out[3, 3] = out[4, 4] = tilt_sigma ** 2
    return out.reshape(36)
