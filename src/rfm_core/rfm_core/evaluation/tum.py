"""ATE and RPE of any TUM-format trajectory against a TUM-format ground truth
(``rfm eval-trajectory``), with the definitions of evo (Grupp, 2017), the tool most SLAM
papers report with; the tests hold the two to 1e-6.

- Files: one pose a line, ``timestamp tx ty tz qx qy qz qw`` (camera to world), ``#``
  comments; what ``rfm run`` writes (``trajectory.tum``) and what TUM RGB-D's
  ``groundtruth.txt`` holds.
- Association (evo's ``sync.associate_trajectories``): each stamp of the shorter trajectory
  takes the nearest stamp of the longer one within ``max_diff`` seconds.
- Alignment of the estimate to the ground truth: ``se3`` (Umeyama, rotation and
  translation), ``sim3`` (and scale: for monocular systems), ``yaw`` (a rotation about z and
  a translation: the 4-DoF of a gravity-aligned map; rfm's maps and TUM's ground truth have
  z up; not in evo) or ``none``.
- APE (evo_ape): per pose, the translation ``|t_est - t_ref|`` and the rotation angle of
  ``inv(P_ref) P_est``; ATE is the APE translation's RMSE.
- RPE (evo_rpe, ``delta`` frames, pairs (0, d), (d, 2d), ...): per pair,
  ``E = inv(inv(Q_i) Q_j) inv(P_i) P_j``; its translation's norm and rotation angle.
- Statistics of each: rmse, mean, median, std (population), min, max, sse.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rfm_core.evaluation.trajectory import umeyama
from rfm_core.geometry import kabsch_4dof, matrix_from_quaternion

__all__ = ['ALIGNMENTS', 'read_tum', 'associate', 'align', 'ape', 'rpe', 'statistics', 'evaluate_tum']

ALIGNMENTS = ('se3', 'sim3', 'yaw', 'none')


def read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,) s, poses (N, 4, 4) camera to world) of a TUM trajectory file; ValueError
    naming the line for anything that is not 8 finite numbers with a non-zero quaternion."""
    stamps, rows = [], []
    for number, line in enumerate(Path(path).read_text().splitlines(), 1):
        text = line.split('#', 1)[0].replace(',', ' ').split()
        if not text:
            continue
        try:
            values = [float(v) for v in text]
        except ValueError:
            values = []
        if len(values) != 8 or not np.all(np.isfinite(values)) or np.linalg.norm(values[4:]) < 1e-9:
            raise ValueError(f'{path}:{number}: expected "timestamp tx ty tz qx qy qz qw", got {line.strip()!r}')
        stamps.append(values[0])
        rows.append(values[1:])
    if not rows:
        raise ValueError(f'{path}: no poses')
    rows = np.array(rows)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = matrix_from_quaternion(rows[:, 3:])            # x y z w, normalised
    poses[:, :3, 3] = rows[:, :3]
    return np.array(stamps), poses


def _nearest(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float) -> tuple[list, list]:
    """evo's ``matching_time_indices``: each stamp of the first, the nearest of the second."""
    first, second = [], []
    for i, stamp in enumerate(stamps_1):
        diffs = np.abs(stamps_2 - stamp)
        j = int(np.argmin(diffs))
        if diffs[j] <= max_diff:
            first.append(i)
            second.append(j)
    return first, second


def associate(stamps_ref: np.ndarray, stamps_est: np.ndarray, max_diff: float = 0.01) -> tuple:
    """(indices into the reference, indices into the estimate) of the associated poses."""
    if len(stamps_est) > len(stamps_ref):
        ref, est = _nearest(stamps_ref, stamps_est, max_diff)
    else:
        est, ref = _nearest(stamps_est, stamps_ref, max_diff)
    return np.array(ref, int), np.array(est, int)


def align(est: np.ndarray, ref: np.ndarray, mode: str = 'se3') -> tuple[np.ndarray, float]:
    """(the estimated poses (N, 4, 4) aligned to the reference ones, the scale applied)."""
    if mode not in ALIGNMENTS:
        raise ValueError(f'alignment {mode!r}: choose one of {", ".join(ALIGNMENTS)}')
    if mode == 'none':
        return est.copy(), 1.0
    if len(est) < 3:
        raise ValueError(f'{mode} alignment needs three associated poses or more, got {len(est)}')
    if mode == 'yaw':
        m = kabsch_4dof(est[:, :3, 3], ref[:, :3, 3]).matrix()
        r, t, c = m[:3, :3], m[:3, 3], 1.0
    else:
        r, t, c = umeyama(est[:, :3, 3], ref[:, :3, 3], with_scale=mode == 'sim3')
    out = est.copy()
    out[:, :3, :3] = r @ est[:, :3, :3]
    out[:, :3, 3] = (c * est[:, :3, 3]) @ r.T + t
    return out, c


def _angle_deg(rotations: np.ndarray) -> np.ndarray:
    cos = (np.trace(rotations, axis1=1, axis2=2) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def ape(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation errors (m), rotation errors (deg)) of associated, aligned poses."""
    relative = np.linalg.inv(ref) @ est
    return np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1), _angle_deg(relative[:, :3, :3])


def rpe(est: np.ndarray, ref: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(translation errors (m), rotation errors (deg)) of the relative poses over ``delta``
    frames, pairs (0, delta), (delta, 2 delta), ..."""
    if delta < 1:
        raise ValueError(f'delta must be at least one frame, got {delta}')
    ids = np.arange(0, len(est), delta)
    i, j = ids[:-1], ids[1:]
    errors = np.linalg.inv(np.linalg.inv(ref[i]) @ ref[j]) @ (np.linalg.inv(est[i]) @ est[j])
    return np.linalg.norm(errors[:, :3, 3], axis=1), _angle_deg(errors[:, :3, :3])


def statistics(errors: np.ndarray) -> dict:
    """evo's statistics of an error array (NaN for none)."""
    e = np.asarray(errors, float)
    if not len(e):
        return {k: float('nan') for k in ('rmse', 'mean', 'median', 'std', 'min', 'max', 'sse')}
    return {'rmse': float(np.sqrt(np.mean(e ** 2))), 'mean': float(e.mean()), 'median': float(np.median(e)),
            'std': float(e.std()), 'min': float(e.min()), 'max': float(e.max()), 'sse': float(np.sum(e ** 2))}


def evaluate_tum(trajectory, ground_truth, alignment: str = 'se3', delta: int = 1, max_diff: float = 0.01) -> dict:
    """APE and RPE statistics of a TUM trajectory file against a ground-truth one."""
    stamps_est, est = read_tum(trajectory)
    stamps_ref, ref = read_tum(ground_truth)
    i_ref, i_est = associate(stamps_ref, stamps_est, max_diff)
    if not len(i_ref):
        raise ValueError(f'no pose of {trajectory} is within {max_diff} s of one of {ground_truth}: '
                         'are both stamped by the same clock, in seconds?')
    ref, est = ref[i_ref], est[i_est]
    aligned, scale = align(est, ref, alignment)
    ape_t, ape_r = ape(aligned, ref)
    rpe_t, rpe_r = rpe(aligned, ref, delta)       # as evo_rpe on the aligned estimate (sim3 scales it)
    return {'trajectory': str(trajectory), 'ground_truth': str(ground_truth), 'alignment': alignment,
            'scale': scale, 'poses': len(stamps_est), 'ground_truth_poses': len(stamps_ref), 'associated': len(i_ref),
            'max_diff_s': max_diff, 'delta_frames': delta,
            'ape_translation_m': statistics(ape_t), 'ape_rotation_deg': statistics(ape_r),
            'rpe_translation_m': statistics(rpe_t), 'rpe_rotation_deg': statistics(rpe_r)}
