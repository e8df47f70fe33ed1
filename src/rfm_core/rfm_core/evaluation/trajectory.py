"""Localization accuracy as in the paper: ATE and ARE after alignment, and registration.

Estimated camera poses (camera-to-map, 4x4) are aligned to the ground truth without scale
(boxes are metric): by default with the 4-DoF transform (yaw about gravity + translation)
that best fits the camera centres and a point 1 m along each optical axis — the map frame
is gravity-aligned by construction, so this is the paper's SE(3) alignment without the
tilt, and with orientations in the fit so that a short or nearly straight trajectory does
not leave the yaw undetermined (``align='se3'``: the general fit of the centres). The fit is
robust (:func:`align_robust`): it is made on the frames most of the trajectory agrees with, so
a wrongly placed part (one wrong registration moves many frames together) neither drags the
right frames off nor hides among them. ATE is the distance between aligned and true camera
centres, ARE the angle of the relative rotation; ``wrong`` counts the frames off by more than
:data:`GROSS` (the gross errors every evaluation reports). Frames the system did not register
count in ``registered`` only.
"""
from __future__ import annotations

import numpy as np

from rfm_core.geometry import Pose4

__all__ = ['GROSS', 'TWO_SIGMA', 'umeyama', 'align_se3', 'align_4dof', 'align_robust', 'map_to_truth',
           'trajectory_errors', 'covariance_coverage', 'frame_errors']

#: a pose off by more than this is wrong (deg, m): the gross errors every evaluation counts
GROSS = (5.0, 0.25)
#: the 4-DoF (x, y, z, heading) Mahalanobis distance^2 within which a Gaussian error lies as
#: often as a 1-D one within two sigmas (95.45%: the chi-square quantile with 4 degrees of freedom)
TWO_SIGMA = 9.72


def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool) -> tuple:
    """(R, t, c) minimising sum |y_i - (c R x_i + t)|^2 over points (N, 3) (Umeyama, 1991;
    R a proper rotation, c = 1 without ``with_scale``)."""
    mean_x, mean_y = x.mean(0), y.mean(0)
    u, d, vt = np.linalg.svd((y - mean_y).T @ (x - mean_x) / len(x))
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    r = u @ s @ vt
    c = float(np.trace(np.diag(d) @ s) / np.mean(np.sum((x - mean_x) ** 2, axis=1))) if with_scale else 1.0
    return r, mean_y - c * r @ mean_x, c


def align_se3(source: np.ndarray, target: np.ndarray):
    """(R, t) minimising sum |R source_i + t - target_i|^2 (proper rotation)."""
    source = np.asarray(source, float).reshape(-1, 3)
    target = np.asarray(target, float).reshape(-1, 3)
    if len(source) == 0:
        return np.eye(3), np.zeros(3)
    if len(source) < 3:
        return np.eye(3), target.mean(0) - source.mean(0)
    return umeyama(source, target, with_scale=False)[:2]


def align_4dof(est: np.ndarray, gt: np.ndarray, lever_m: float = 1.0):
    """(R, t), R a rotation about z, best mapping estimated poses (N, 4, 4) onto true ones:
    the yaw fits the camera centres and, ``lever_m`` ahead of each, a point on its optical
    axis (so orientations count too: a short or straight trajectory leaves the yaw of a
    centres-only fit poorly determined); t aligns the centroids of the centres."""
    ce, cg = est[:, :3, 3], gt[:, :3, 3]
    pe = np.concatenate([ce, ce + lever_m * est[:, :3, 2]])
    pg = np.concatenate([cg, cg + lever_m * gt[:, :3, 2]])
    a, b = pe[:, :2] - pe[:, :2].mean(0), pg[:, :2] - pg[:, :2].mean(0)
    yaw = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
    c, s = np.cos(yaw), np.sin(yaw)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r, cg.mean(0) - r @ ce.mean(0)


def _errors(est: np.ndarray, gt: np.ndarray, r: np.ndarray, t: np.ndarray) -> tuple:
    """(ATE (m), ARE (deg)) of each estimated pose (N, 4, 4) under the alignment (r, t)."""
    ate = np.linalg.norm(est[:, :3, 3] @ r.T + t - gt[:, :3, 3], axis=1)
    rel = np.einsum('nji,njk->nik', gt[:, :3, :3], np.einsum('ij,njk->nik', r, est[:, :3, :3]))
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return ate, np.degrees(np.arccos(cos))


def align_robust(est: np.ndarray, gt: np.ndarray, gross=GROSS, hypotheses: int = 200):
    """(R, t) as :func:`align_4dof`, fitted on the frames the trajectory's consensus holds: each
    of up to ``hypotheses`` frames proposes the 4-DoF alignment that lays it on its truth;
    the proposal under which most frames are within ``gross`` (deg, m) wins, and the fit is
    redone on those frames (twice). A refit that holds fewer than half the frames it was
    fitted on is no fit of them and is not kept (a trajectory in two parts a few decimetres
    apart pulled the least-squares fit between them and put every frame a few degrees off).
    Without a consensus of two frames: the fit on all."""
    n = len(est)
    if n < 3:
        return align_4dof(est, gt)
    step = max(1, n // hypotheses)
    best, best_count = None, 1
    for i in range(0, n, step):
        d = gt[i, :3, :3] @ est[i, :3, :3].T
        yaw = np.arctan2(d[1, 0] - d[0, 1], d[0, 0] + d[1, 1])
        c, s = np.cos(yaw), np.sin(yaw)
        r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        proposal = (r, gt[i, :3, 3] - r @ est[i, :3, 3])
        ate, are = _errors(est, gt, *proposal)
        inliers = (ate <= gross[1]) & (are <= gross[0])
        if inliers.sum() > best_count:
            best, best_count, kept = inliers, int(inliers.sum()), proposal
    if best is None:
        return align_4dof(est, gt)
    for _ in range(3):
        fit = align_4dof(est[best], gt[best])
        ate, are = _errors(est, gt, *fit)
        inliers = (ate <= gross[1]) & (are <= gross[0])
        if 2 * inliers.sum() < best_count or inliers.sum() < 2:
            break
        best, best_count, kept = inliers, int(inliers.sum()), fit
    return kept


def _matched(estimated: dict, truth: dict):
    """The frames in both, and their (N, 4, 4) estimated and true poses."""
    keys = [k for k in truth if k in estimated]
    est = np.array([estimated[k] for k in keys], float).reshape(-1, 4, 4)
    gt = np.array([truth[k] for k in keys], float).reshape(-1, 4, 4)
    return keys, est, gt


def map_to_truth(estimated: dict, truth: dict) -> Pose4:
    """T_truth_map: the 4-DoF alignment :func:`trajectory_errors` applies by default (for
    expressing a map's boxes in the truth's frame); identity without common frames."""
    _, est, gt = _matched(estimated, truth)
    if not len(est):
        return Pose4(0.0, (0.0, 0.0, 0.0))
    r, t = align_robust(est, gt)
    return Pose4(float(np.arctan2(r[1, 0], r[0, 0])), t)


def _alignment(est: np.ndarray, gt: np.ndarray, align: str | bool) -> tuple:
    """(R, t) laying ``est`` on ``gt`` as ``align`` says (see :func:`trajectory_errors`)."""
    if align == 'se3':
        return align_se3(est[:, :3, 3], gt[:, :3, 3])
    if align:
        return align_robust(est, gt)
    return np.eye(3), np.zeros(3)


def trajectory_errors(estimated: dict, truth: dict, align: str | bool = '4dof') -> dict:
    """``estimated`` / ``truth``: {frame key: 4x4 camera-to-map}. Errors over the frames
    present in both; ``registered`` = share of ``truth`` frames that were estimated;
    ``wrong`` = share of the estimated frames off by more than :data:`GROSS`, ``gross`` their
    number. ``align``: '4dof' (default: :func:`align_robust`), 'se3', or False (posed:
    already in the truth's frame)."""
    keys, est, gt = _matched(estimated, truth)
    out = {'frames': len(truth), 'registered': len(keys) / max(len(truth), 1), 'wrong': 0.0, 'gross': 0}
    if not keys:
        out.update(ATE_median=float('nan'), ATE_rmse=float('nan'), ARE_median=float('nan'),
                   ARE_rmse=float('nan'))
        return out
    r, t = _alignment(est, gt, align)
    ate, are = _errors(est, gt, r, t)
    gross = (are > GROSS[0]) | (ate > GROSS[1])
    out.update(ATE_median=float(np.median(ate)), ATE_rmse=float(np.sqrt(np.mean(ate ** 2))),
               ARE_median=float(np.median(are)), ARE_rmse=float(np.sqrt(np.mean(are ** 2))),
               wrong=float(np.mean(gross)), gross=int(gross.sum()))
    return out


def frame_errors(estimated: dict, truth: dict) -> dict:
    """{frame key: (ATE m, ARE deg)} of each frame in both, not aligned (poses already in the
    truth's frame)."""
    keys, est, gt = _matched(estimated, truth)
    ate, are = _errors(est, gt, np.eye(3), np.zeros(3))
    return {k: (float(a), float(r)) for k, a, r in zip(keys, ate, are)}


def covariance_coverage(estimated: dict, covariances: dict, truth: dict, align: str | bool = '4dof') -> dict:
    """How well the poses' covariances bound their errors. ``covariances``: {frame key: (6, 6)
    PoseWithCovariance order} of the ``estimated`` frames. Each frame's error (position in the
    map's axes, heading about its z) under the alignment :func:`trajectory_errors` applies,
    against its 4-DoF block: ``within_2sigma`` the share of frames whose Mahalanobis distance^2
    is at most :data:`TWO_SIGMA` (a calibrated covariance: about 0.95), ``sigma_m`` /
    ``sigma_deg`` the median position (RMS over the axes) and heading standard deviations."""
    keys = [k for k in truth if k in estimated and covariances.get(k) is not None]
    out = {'frames': len(keys), 'within_2sigma': float('nan'), 'sigma_m': float('nan'), 'sigma_deg': float('nan')}
    if not keys:
        return out
    est = np.array([estimated[k] for k in keys], float).reshape(-1, 4, 4)
    gt = np.array([truth[k] for k in keys], float).reshape(-1, 4, 4)
    r, t = _alignment(est, gt, align)
    e_pos = np.einsum('ji,nj->ni', r, est[:, :3, 3] @ r.T + t - gt[:, :3, 3])          # in the map's axes
    d = np.einsum('nij,nkj->nik', np.einsum('ij,njk->nik', r, est[:, :3, :3]), gt[:, :3, :3])   # R_est R_gt^T
    e_yaw = np.arctan2(d[:, 1, 0] - d[:, 0, 1], d[:, 0, 0] + d[:, 1, 1])                # its turn about z
    cov = np.array([np.asarray(covariances[k], float).reshape(6, 6)[np.ix_([0, 1, 2, 5], [0, 1, 2, 5])]
                    for k in keys])
    err = np.c_[e_pos, e_yaw]
    d2 = np.einsum('ni,ni->n', err, np.linalg.solve(cov + 1e-12 * np.eye(4), err[..., None])[..., 0])
    out.update(within_2sigma=float(np.mean(d2 <= TWO_SIGMA)),
               sigma_m=float(np.median(np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2) / 3))),
               sigma_deg=float(np.degrees(np.median(np.sqrt(cov[:, 3, 3])))))
    return out
