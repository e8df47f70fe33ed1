"""Conversions between rfm_core types and ROS messages.

Functions that *read* messages only use their fields, so they work on any object shaped
like the message (and in tests without ROS). Functions that *build* messages import the
message classes lazily: rfm_core itself stays importable without ROS.
"""
from __future__ import annotations

import array

import numpy as np

from rfm_core.geometry import (
    Pose4, boxes_from_oriented, gravity_aligned_rotation, matrix_from_quaternion,
    oriented_from_boxes, quaternion_from_matrix,
)
from rfm_core.observations import CameraIntrinsics, FrameObservations

__all__ = [
    'stamp_to_ns', 'ns_to_stamp', 'pose_to_matrix', 'matrix_to_pose', 'pose_to_pose4',
    'pose4_to_pose', 'vector3_to_numpy', 'float32_array', 'frame_detections_from_msg',
    'frame_detections_to_msg',
]

_NS = 1_000_000_000


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def ns_to_stamp(ns: int):
    """Integer nanoseconds -> builtin_interfaces/Time."""
    from builtin_interfaces.msg import Time  # noqa: PLC0415
    ns = int(ns)
    return Time(sec=ns // _NS, nanosec=ns % _NS)


def vector3_to_numpy(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _quat(q) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=np.float64)


def pose_to_matrix(pose) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 matrix. Raises ValueError for a zero or non-finite quaternion."""
    out = np.eye(4)
    out[:3, :3] = matrix_from_quaternion(_quat(pose.orientation))
    out[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    if not np.all(np.isfinite(out)):
        raise ValueError('pose has a non-finite position')
    return out


def matrix_to_pose(matrix):
    """4x4 matrix -> geometry_msgs/Pose."""
    from geometry_msgs.msg import Point, Pose, Quaternion  # noqa: PLC0415
    m = np.asarray(matrix, dtype=np.float64)
    q = quaternion_from_matrix(m[:3, :3])
    return Pose(position=Point(x=float(m[0, 3]), y=float(m[1, 3]), z=float(m[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def pose_to_pose4(pose, atol: float = 1e-6) -> Pose4:
    """geometry_msgs/Pose whose rotation is a yaw about z -> Pose4."""
    return Pose4.from_matrix(pose_to_matrix(pose), atol=atol)


def pose4_to_pose(pose4: Pose4):
    """Pose4 -> geometry_msgs/Pose."""
    return matrix_to_pose(pose4.matrix())


def float32_array(values) -> array.array:
    """numpy/sequence -> array.array('f'), the fast way to fill a ROS float32[] field."""
    out = array.array('f')
    out.frombytes(np.ascontiguousarray(values, dtype=np.float32).reshape(-1).tobytes())
    return out


def frame_detections_from_msg(msg) -> FrameObservations:
    """rfm_msgs/FrameDetections -> FrameObservations (boxes in the gravity-aligned frame).

    Validates the message and raises ValueError saying what is wrong: non-positive
    intrinsics or image size, zero gravity, non-finite poses, negative sizes, or
    embeddings of different lengths.
    """
    intrinsics = CameraIntrinsics(float(msg.fx), float(msg.fy), float(msg.cx), float(msg.cy),
                                  int(msg.width), int(msg.height))
    gravity = vector3_to_numpy(msg.gravity)
    obs_rotation = gravity_aligned_rotation(gravity)
    dets = list(msg.detections)
    n = len(dets)
    centers = np.zeros((n, 3))
    rotations = np.zeros((n, 3, 3))
    sizes = np.zeros((n, 3))
    for i, det in enumerate(dets):
        m = pose_to_matrix(det.pose)
        centers[i] = obs_rotation @ m[:3, 3]
        rotations[i] = obs_rotation @ m[:3, :3]
        sizes[i] = vector3_to_numpy(det.size)
    if not np.all(np.isfinite(sizes)) or np.any(sizes < 0):
        raise ValueError('detection sizes must be finite and non-negative')
    dims = {len(d.embedding) for d in dets}
    if len(dims) > 1:
        raise ValueError(f'detections have embeddings of different lengths {sorted(dims)}')
    dim = dims.pop() if dims else 0
    embeddings = (np.array([np.asarray(d.embedding, dtype=np.float32) for d in dets])
                  if n and dim else np.zeros((n, 0), np.float32))
    corner = None
    corner_lengths = {len(d.corner_descriptors) for d in dets}
    if n and corner_lengths != {0}:
        if len(corner_lengths) > 1 or next(iter(corner_lengths)) % 8:
            raise ValueError('corner_descriptors must be 8 x D for every detection or empty for all')
        corner = np.array([np.asarray(d.corner_descriptors, np.float32).reshape(8, -1) for d in dets])
    return FrameObservations(
        stamp_ns=stamp_to_ns(msg.header.stamp),
        frame_id=msg.header.frame_id,
        intrinsics=intrinsics,
        gravity_cam=gravity,
        boxes=boxes_from_oriented(centers, rotations, sizes),
        scores=np.array([d.score for d in dets], dtype=np.float32),
        labels=[d.label for d in dets],
        embeddings=embeddings,
        boxes_2d=np.array([np.asarray(d.box_2d, np.float32) for d in dets]).reshape(n, 4),
        visibility=np.array([d.visibility for d in dets], dtype=np.float32),
        object_ids=np.array([d.object_id for d in dets], dtype=np.int64),
        corner_descriptors=corner,
        backend=msg.backend,
    )


def frame_detections_to_msg(obs: FrameObservations):
    """FrameObservations -> rfm_msgs/FrameDetections (box poses in the camera optical frame)."""
    from geometry_msgs.msg import Vector3  # noqa: PLC0415
    from rfm_msgs.msg import FrameDetections, ObjectDetection  # noqa: PLC0415
    from std_msgs.msg import Header  # noqa: PLC0415

    camera_from_aligned = obs.rotation_aligned_from_camera.T
    centers, rotations, sizes = oriented_from_boxes(obs.boxes)
    msg = FrameDetections(
        header=Header(stamp=ns_to_stamp(obs.stamp_ns), frame_id=obs.frame_id),
        backend=obs.backend,
        fx=float(obs.intrinsics.fx), fy=float(obs.intrinsics.fy),
        cx=float(obs.intrinsics.cx), cy=float(obs.intrinsics.cy),
        width=int(obs.intrinsics.width), height=int(obs.intrinsics.height),
        gravity=Vector3(x=float(obs.gravity_cam[0]), y=float(obs.gravity_cam[1]),
                        z=float(obs.gravity_cam[2])),
    )
    detections = []
    for i in range(len(obs)):
        m = np.eye(4)
        m[:3, :3] = camera_from_aligned @ rotations[i]
        m[:3, 3] = camera_from_aligned @ centers[i]
        det = ObjectDetection(
            index=i,
            object_id=int(obs.object_ids[i]),
            pose=matrix_to_pose(m),
            size=Vector3(x=float(sizes[i, 0]), y=float(sizes[i, 1]), z=float(sizes[i, 2])),
            score=float(obs.scores[i]),
            label=obs.labels[i],
            box_2d=obs.boxes_2d[i].astype(np.float32),
            visibility=float(obs.visibility[i]),
        )
        det.embedding = float32_array(obs.embeddings[i])
        if obs.corner_descriptors is not None:
            det.corner_descriptors = float32_array(obs.corner_descriptors[i])
        detections.append(det)
    msg.detections = detections
    return msg
