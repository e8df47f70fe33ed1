"""`rfm eval-trajectory`: ATE and RPE of TUM files agree with evo's to 1e-6."""
import json
import shutil
import subprocess

import numpy as np
import pytest
from evo.core import metrics as evo_metrics         # a test dependency (requirements.txt)
from scipy.spatial.transform import Rotation

from rfm_core.evaluation.tum import align, evaluate_tum, read_tum


def _walk(n: int, seed: int) -> np.ndarray:
    """(n, 4, 4) camera poses of a smooth walk with changing heading, pitch and roll."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 20, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.c_[2 * np.cos(0.3 * t), 1.5 * np.sin(0.4 * t), 1.2 + 0.1 * np.sin(t)]
    angles = np.c_[0.3 * t + 0.2 * np.sin(t), 0.05 * np.sin(0.7 * t), 0.08 * np.cos(0.5 * t)]
    poses[:, :3, :3] = Rotation.from_euler('zyx', angles + rng.normal(0, 1e-3, (n, 3))).as_matrix()
    return poses


def _write_tum(path, stamps, poses):
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    lines = ['# timestamp tx ty tz qx qy qz qw'] + [
        ' '.join(f'{v:.9f}' for v in (s, *p[:3, 3], *qq)) for s, p, qq in zip(stamps, poses, q)]
    path.write_text('\n'.join(lines) + '\n')
    return path


@pytest.fixture
def files(tmp_path):
    """A ground truth at 100 Hz and an estimate at 30 Hz, 3 ms off the truth's clock, in
    another frame and at another scale, with noise and one gross error."""
    rng = np.random.default_rng(7)
    truth_stamps = 1_700_000_000 + np.arange(0, 20, 0.01)
    truth = _walk(len(truth_stamps), seed=1)
    pick = np.arange(0, len(truth_stamps), 3)[:-1]
    est_stamps = truth_stamps[pick] + 0.003
    est = truth[pick].copy()
    est[:, :3, 3] += rng.normal(0, 0.02, (len(pick), 3))
    est[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (len(pick), 3))).as_matrix() @ est[:, :3, :3]
    est[40, :3, 3] += [0.5, -0.3, 0.2]
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_euler('zyx', [1.1, 0.2, -0.3]).as_matrix()
    frame[:3, 3] = [3.0, -1.0, 0.5]
    est = frame @ est
    est[:, :3, 3] *= 0.8
    return (_write_tum(tmp_path / 'est.tum', est_stamps, est), _write_tum(tmp_path / 'gt.tum', truth_stamps, truth))


def _evo(est_path, gt_path, alignment: str, delta: int):
    from evo.core import sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    if alignment != 'none':
        est.align(ref, correct_scale=alignment == 'sim3')
    out = {}
    for name, metric in (('ape_translation_m', evo_metrics.APE(evo_metrics.PoseRelation.translation_part)),
                         ('ape_rotation_deg', evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)),
                         ('rpe_translation_m', evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, delta,
                                                               evo_metrics.Unit.frames, all_pairs=False)),
                         ('rpe_rotation_deg', evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, delta,
                                                              evo_metrics.Unit.frames, all_pairs=False))):
        metric.process_data((ref, est))
        out[name] = metric.get_all_statistics()
    return out, ref.num_poses


@pytest.mark.parametrize('alignment, delta', [('se3', 1), ('sim3', 1), ('none', 5)])
def test_ate_and_rpe_agree_with_evo(files, alignment, delta):
    ours = evaluate_tum(*files, alignment=alignment, delta=delta)
    theirs, associated = _evo(*files, alignment, delta)
    assert ours['associated'] == associated == 666
    for key, stats in theirs.items():
        for name in ('rmse', 'mean', 'median', 'std', 'min', 'max', 'sse'):
            assert ours[key][name] == pytest.approx(stats[name], rel=1e-6, abs=1e-6), (key, name)
    if alignment == 'sim3':
        assert ours['scale'] == pytest.approx(1 / 0.8, rel=1e-2)
        assert ours['ape_translation_m']['median'] < 0.05          # the noise, the gross error aside


def test_yaw_alignment_recovers_a_heading_and_an_offset(files):
    """The 4-DoF alignment of a gravity-aligned map (not in evo): exact for a pure yaw and shift."""
    _, truth = read_tum(files[1])
    moved = truth.copy()
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('z', 2.0).as_matrix()
    turn[:3, 3] = [1.0, 2.0, -0.5]
    moved = turn @ moved
    aligned, scale = align(moved, truth, 'yaw')
    assert scale == 1.0 and np.allclose(aligned, truth, atol=1e-9)


def test_the_command_prints_the_table_and_refuses_bad_files(files, tmp_path):
    rfm = shutil.which('rfm')
    out = subprocess.run([rfm, 'eval-trajectory', *map(str, files), '--align', 'sim3', '--json',
                          str(tmp_path / 'r.json')], capture_output=True, text=True, timeout=60, check=True).stdout
    assert '666 of 666 poses associated' in out and '| APE translation (m): ATE |' in out
    assert json.loads((tmp_path / 'r.json').read_text())['alignment'] == 'sim3'
    (tmp_path / 'bad.tum').write_text('1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n')
    bad = subprocess.run([rfm, 'eval-trajectory', str(tmp_path / 'bad.tum'), str(files[1])],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0 and 'bad.tum:2: expected' in bad.stderr
