"""Every localized frame, compactly: the trajectory at the detector's rate.

Keyframes carry the map; every other processed frame is localized relative to a keyframe
(tracking, :mod:`rfm_core.matching.view_graph`) or relocalized against the map. The log
keeps each frame's pose relative to the keyframe it was localized against, so its camera
pose always follows the keyframe's current (re-averaged) pose. A row never changes once
logged: a frame whose keyframe was culled is placed through the keyframe that carries it
(the mapper's ``merged``), so culling costs nothing here and a map file's frame log can
grow by appending (:mod:`rfm_core.mapping.map_io`). Rows are :data:`ROW` records (86
bytes a frame: 37 MB for 8 hours at 15 Hz), in an array that grows by doubling.
"""
from __future__ import annotations

import numpy as np

from rfm_core.geometry import Pose4, gravity_aligned_rotation
from rfm_core.observations import FrameTrack

__all__ = ['FrameLog', 'ROW', 'camera_to_map', 'pose_from_camera']

#: one logged frame (little-endian, packed: the layout of a map's frame file)
ROW = np.dtype([('stamps', '<i8'), ('keyframes', '<i8'), ('keyframe_stamps', '<i8'), ('poses', '<f8', (4,)),
                ('gravity', '<f8', (3,)), ('inliers', '<i4'), ('is_keyframe', '?'), ('continuous', '?')])


class FrameLog:
    """Append :class:`FrameTrack` records; read camera poses given the keyframe poses."""

    def __init__(self):
        self.clear()

    def clear(self) -> None:
        self._n = 0
        self._rows = np.zeros(16, ROW)
        self.written: dict = {}          # map_io's record of what this log appended where

    def __len__(self) -> int:
        return self._n

    def add(self, track: FrameTrack) -> None:
        if self._n == len(self._rows):
            self._rows = np.concatenate([self._rows, np.zeros_like(self._rows)])
        self._rows[self._n] = (track.stamp_ns, track.keyframe_id, track.keyframe_stamp_ns,
                               (track.pose.yaw, *track.pose.t), track.gravity_cam, track.num_inliers,
                               track.is_keyframe, track.continuous)
        self._n += 1

    def rows(self, start: int = 0) -> np.ndarray:
        """The rows from ``start`` on (a view of :data:`ROW` records)."""
        return self._rows[start:self._n]

    def arrays(self) -> dict:
        """The log as arrays (views, length ``len(self)``), keyed as in the map file."""
        rows = self.rows()
        return {k: rows[k] for k in ROW.names}

    def restore(self, arrays: dict) -> None:
        """Replace the log by ``arrays`` (as from :meth:`arrays`; validated by the caller)."""
        n = len(arrays['stamps'])
        self.clear()
        self._rows = np.zeros(max(16, n), ROW)
        for k in ROW.names:
            self._rows[k][:n] = arrays[k]
        self._n = n

    @staticmethod
    def keyframe_of(keyframe_id: int, keyframe_stamp_ns: int, keyframe_stamps: dict, merged: dict):
        """(the keyframe now carrying frames localized against ``keyframe_id`` at that stamp,
        T_carrier_keyframe or None for itself), or None for a keyframe no longer in the map."""
        if keyframe_stamps.get(keyframe_id) == keyframe_stamp_ns:
            return keyframe_id, None
        m = merged.get(keyframe_id)
        if m is not None and m.stamp_ns == keyframe_stamp_ns:
            return m.into, m.pose
        return None

    def camera_poses(self, keyframe_poses: dict, keyframe_stamps: dict, merged: dict | None = None) -> dict:
        """{stamp_ns: 4x4 camera optical frame -> map} of the frames whose keyframe, or the
        keyframe it was culled into (``merged``: {culled id: Merged}), has a pose in
        ``keyframe_poses`` ({id: Pose4 T_k_map}); ``keyframe_stamps`` ({id: stamp_ns}) tells a
        keyframe from another under a reused id."""
        rows = self.rows()
        merged = merged or {}
        carriers: dict = {}
        out = {}
        for row in rows:
            key = (int(row['keyframes']), int(row['keyframe_stamps']))
            if key not in carriers:
                carriers[key] = self.keyframe_of(*key, keyframe_stamps, merged)
            carrier = carriers[key]
            if carrier is None or carrier[0] not in keyframe_poses:
                continue
            yaw, *t = row['poses']
            t_k_frame = Pose4(yaw, t) if carrier[1] is None else carrier[1] @ Pose4(yaw, t)
            out[int(row['stamps'])] = camera_to_map(t_k_frame.inverse() @ keyframe_poses[carrier[0]], row['gravity'])
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
