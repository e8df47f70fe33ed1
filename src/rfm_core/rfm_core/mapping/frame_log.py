"""Every localized frame, compactly: the trajectory at the detector's rate.

Keyframes carry the map; every other processed frame is localized relative to a keyframe
(tracking, :mod:`rfm_core.matching.view_graph`) or relocalized against the map. The log
keeps each frame's pose relative to its keyframe, so its camera pose always follows the
keyframe's current (re-averaged) pose. Arrays grow by doubling: about 80 bytes a frame,
30 MB for an hour at 30 Hz.
"""
from __future__ import annotations

import numpy as np

from rfm_core.geometry import Pose4, gravity_aligned_rotation
from rfm_core.observations import FrameTrack

__all__ = ['FrameLog', 'camera_to_map', 'pose_from_camera']

_FIELDS = {'stamps': ((), np.int64), 'keyframes': ((), np.int64), 'keyframe_stamps': ((), np.int64),
           'poses': ((4,), np.float64),
           'gravity': ((3,), np.float64), 'inliers': ((), np.int32), 'is_keyframe': ((), bool),
           'continuous': ((), bool)}


class FrameLog:
    """Append :class:`FrameTrack` records; read camera poses given the keyframe poses."""

    def __init__(self):
        self.clear()

    def clear(self) -> None:
        self._n = 0
        self._data = {k: np.zeros((16, *shape), dtype) for k, (shape, dtype) in _FIELDS.items()}

    def __len__(self) -> int:
        return self._n

    def add(self, track: FrameTrack) -> None:
        if self._n == len(self._data['stamps']):
            self._data = {k: np.concatenate([v, np.zeros_like(v)]) for k, v in self._data.items()}
        i = self._n
        d = self._data
        d['stamps'][i], d['keyframes'][i] = track.stamp_ns, track.keyframe_id
        d['keyframe_stamps'][i] = track.keyframe_stamp_ns
        d['poses'][i] = (track.pose.yaw, *track.pose.t)
        d['gravity'][i] = track.gravity_cam
        d['inliers'][i], d['is_keyframe'][i], d['continuous'][i] = (
            track.num_inliers, track.is_keyframe, track.continuous)
        self._n += 1

    def merge(self, keyframe_id: int, keyframe_stamp_ns: int, into: int, into_stamp_ns: int, t_into_keyframe: Pose4):
        """Frames localized against a keyframe culled from the map, now against the keyframe
        ``into`` it was merged into (``t_into_keyframe``: T_into_keyframe)."""
        d = self.arrays()
        rows = np.flatnonzero((d['keyframes'] == keyframe_id) & (d['keyframe_stamps'] == keyframe_stamp_ns))
        for i in rows:
            yaw, *t = d['poses'][i]
            p = t_into_keyframe @ Pose4(yaw, t)
            d['poses'][i] = (p.yaw, *p.t)
        d['keyframes'][rows], d['keyframe_stamps'][rows], d['is_keyframe'][rows] = into, into_stamp_ns, False

    def arrays(self) -> dict:
        """The log as arrays (views, length ``len(self)``), keyed as in the map file."""
        return {k: v[:self._n] for k, v in self._data.items()}

    def restore(self, arrays: dict) -> None:
        """Replace the log by ``arrays`` (as from :meth:`arrays`; validated by the caller)."""
        n = len(arrays['stamps'])
        self._n = 0
        self._data = {k: np.zeros((max(16, n), *shape), dtype) for k, (shape, dtype) in _FIELDS.items()}
        for k in _FIELDS:
            self._data[k][:n] = arrays[k]
        self._n = n

    def camera_poses(self, keyframe_poses: dict, keyframe_stamps: dict) -> dict:
        """{stamp_ns: 4x4 camera optical frame -> map} of the frames whose keyframe has a pose
        in ``keyframe_poses`` ({id: Pose4 T_k_map}) and the stamp it was localized against
        (``keyframe_stamps``: {id: stamp_ns}; another keyframe under a reused id is not it)."""
        d = self.arrays()
        out = {}
        for i in range(self._n):
            k = int(d['keyframes'][i])
            p = keyframe_poses.get(k)
            if p is not None and keyframe_stamps.get(k) == int(d['keyframe_stamps'][i]):
                yaw, *t = d['poses'][i]
                out[int(d['stamps'][i])] = camera_to_map(Pose4(yaw, t).inverse() @ p, d['gravity'][i])
        return out


def camera_to_map(t_frame_map: Pose4, gravity_cam) -> np.ndarray:
    """4x4 pose of a camera optical frame in the map from its 4-DoF pose T_frame_map (of its
    gravity-aligned frame) and its gravity ("down" in the optical frame)."""
    m = t_frame_map.inverse().matrix()
    out = np.eye(4)
    out[:3, :3] = m[:3, :3] @ gravity_aligned_rotation(np.asarray(gravity_cam, float))
    out[:3, 3] = m[:3, 3]
    return out


def pose_from_camera(camera_to_map_matrix, gravity_cam, atol: float = 0.05) -> Pose4:
    """The inverse of :func:`camera_to_map`: T_frame_map of a frame whose camera optical frame
    is at ``camera_to_map_matrix`` (4x4) in the map. ValueError when that orientation and the
    frame's gravity disagree by more than about ``atol`` rad (a pose from another source
    whose roll or pitch is not the frame's)."""
    cam = np.asarray(camera_to_map_matrix, float)
    r = gravity_aligned_rotation(np.asarray(gravity_cam, float)) @ cam[:3, :3].T
    t_k_map = np.eye(4)
    t_k_map[:3, :3], t_k_map[:3, 3] = r, -r @ cam[:3, 3]
    return Pose4.from_matrix(t_k_map, atol=atol)
