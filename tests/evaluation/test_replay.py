"""What the detector leaves a photo collection: the detections of each frame that another frame
also detected, placed in the world by the true camera poses."""
import numpy as np
from scipy.spatial.transform import Rotation

from rfm_core.evaluation.replay import shared_detections
from rfm_core.geometry import gravity_aligned_rotation
from rfm_core.observations import CameraIntrinsics, FrameObservations

INTRINSICS = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)
OBJECTS = np.array([[1.0, 2.0, 0.4], [2.5, 2.2, 0.5], [1.8, 3.5, 0.9], [4.0, 1.0, 0.3], [5.0, 3.0, 0.6],
                    [0.5, 5.0, 0.2]])


def _camera(yaw_deg: float, pitch_deg: float, centre) -> np.ndarray:
    """4x4 camera optical frame -> world (z up): looking along ``yaw`` and down by ``pitch``."""
    optical_in_body = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float).T   # x right, y down, z forward
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler('zy', [yaw_deg, pitch_deg], degrees=True).as_matrix() @ optical_in_body
    pose[:3, 3] = centre
    return pose


def _frame(stamp_ns: int, pose: np.ndarray, seen: list) -> FrameObservations:
    """The detections of ``OBJECTS[seen]`` from camera ``pose``."""
    gravity = pose[:3, :3].T @ np.array([0.0, 0.0, -1.0])                      # down, in the camera frame
    centres = (OBJECTS[seen] - pose[:3, 3]) @ pose[:3, :3]             # R^T (p - t), as rows
    boxes = np.zeros((len(seen), 7))
    boxes[:, :3] = centres @ gravity_aligned_rotation(gravity).T
    boxes[:, 3:6] = 0.4
    return FrameObservations(stamp_ns, 'camera', INTRINSICS, gravity, boxes, np.ones(len(seen)))


def test_a_frame_counts_the_detections_another_frame_also_detected():
    truth = {1: _camera(80, 20, (1.5, 0.0, 1.5)), 2: _camera(40, 35, (0.5, 0.5, 1.4)),
             3: _camera(170, 10, (6.0, 2.0, 1.6)), 4: _camera(100, 25, (1.0, 1.0, 1.5))}
    frames = [_frame(1, truth[1], [0, 1, 2]), _frame(2, truth[2], [0, 1, 2, 3]), _frame(3, truth[3], [3, 4]),
              _frame(4, truth[4], [5]), _frame(5, truth[1], [0, 1])]
    shared = shared_detections(frames, truth)
    # frame 5 has no true pose; no other frame saw frame 4's one object
    assert shared == {1: 3, 2: 4, 3: 1, 4: 0}
    # an object placed 0.5 m off by a wrong true pose is no longer the one the others saw
    off = np.eye(4)
    off[0, 3] = 0.5
    assert shared_detections(frames, {**truth, 1: truth[1] @ off})[1] == 0
