"""Conversions between rfm_core types and ROS messages.

Functions that *read* messages only use their fields, so they work on any object shaped
like the message (rclpy messages, rosbags messages, test doubles). Functions that *build*
messages take a factory ``make``: :data:`ROS` builds rclpy messages (imported lazily, so
rfm_core stays importable without ROS), :class:`BagMessages` builds ``rosbags`` messages
for writing bags without ROS. Builders always pass every field, as rosbags requires.
"""
from __future__ import annotations

import array
import functools
import importlib

import numpy as np

from rfm_core.geometry import (
    BOX_EDGES, Pose4, box_corners, boxes_from_oriented, gravity_aligned_rotation, matrix_from_quaternion,
    oriented_from_boxes, quaternion_from_matrix,
)
from rfm_core.clouds import MAX_CLOUD_POINTS
from rfm_core.observations import CameraIntrinsics, EdgeRecord, FrameObservations, FrameTrack

__all__ = [
    'ROS', 'RosMessages', 'BagMessages', 'ros_message_class', 'header', 'pose_stamped_msg', 'transform_stamped_msg',
    'camera_info_msg', 'imu_msg', 'object_map_msg', 'box_markers_msg',
    'camera_info_intrinsics', 'imu_reading',
    'stamp_to_ns', 'ns_to_stamp', 'pose_to_matrix', 'matrix_to_pose', 'pose_to_pose4',
    'pose4_to_pose', 'vector3_to_numpy', 'float32_array', 'frame_detections_from_msg',
    'frame_detections_to_msg', 'tracked_frame_to_msg', 'attachment_msg', 'transforms_from_msg',
    'odometry_msg', 'planar_matrix', 'tracked_frame_from_msg', 'edge_msg', 'edge_record_from_msg',
    'transform_to_matrix', 'track_colour', 'track_map_msgs', 'keyframe_pose_outputs', 'camera_pose_outputs',
    'object_map_outputs', 'tick_outputs', 'pose_with_covariance_msg', 'mapper_status_msg', 'relocalize_answer',
    'detection_markers_msg', 'diagnostics_msg',
]

MAX_DETECTIONS = 1000       #: detections read from one frame message (the detectors' max_detections bound)
MAX_WALLS = 64              #: walls read from one frame message
MAX_DESCRIPTOR_DIM = 4096   #: values in one embedding, or per corner descriptor (CuTR: 256)

_NS = 1_000_000_000


@functools.lru_cache(maxsize=None)
def ros_message_class(typename: str):
    """The rclpy class of 'pkg/msg/Type' (or 'pkg/Type'), looked up once. Raises LookupError
    saying what to do when the type is not installed."""
    parts = typename.split('/')
    if len(parts) == 2:                       # pkg/Type (ROS 1 style names)
        parts = [parts[0], 'msg', parts[1]]
    package, kind, name = parts
    try:
        return getattr(importlib.import_module(f'{package}.{kind}'), name)
    except (ImportError, AttributeError) as exc:
        raise LookupError(f"message type '{typename}' is not installed ({exc}); "
                          'source the workspace that provides it') from exc


class RosMessages:
    """Builds messages as rclpy message objects (needs ROS): ``make('pkg/msg/Type', **fields)``."""

    def __call__(self, typename: str, **fields):
        return ros_message_class(typename)(**fields)

    @staticmethod
    def uint8_array(values: np.ndarray):
        out = array.array('B')
        out.frombytes(np.ascontiguousarray(values, dtype=np.uint8).tobytes())
        return out

    @staticmethod
    def float32_array(values) -> array.array:
        return float32_array(values)


class BagMessages:
    """Builds messages as ``rosbags`` typestore objects (no ROS needed), for bag writing."""

    def __init__(self, typestore):
        self.typestore = typestore

    def __call__(self, typename: str, **fields):
        return self.typestore.types[typename](**fields)

    @staticmethod
    def uint8_array(values: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(values, dtype=np.uint8).reshape(-1)

    @staticmethod
    def float32_array(values) -> np.ndarray:
        return np.ascontiguousarray(values, dtype=np.float32).reshape(-1)


ROS = RosMessages()


def header(make, stamp_ns: int, frame_id: str):
    """std_msgs/Header."""
    ns = int(stamp_ns)
    return make('std_msgs/msg/Header',
                stamp=make('builtin_interfaces/msg/Time', sec=ns // _NS, nanosec=ns % _NS),
                frame_id=frame_id)


def _vector3(make, v):
    return make('geometry_msgs/msg/Vector3', x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _pose(make, matrix):
    m = np.asarray(matrix, dtype=np.float64)
    q = quaternion_from_matrix(m[:3, :3])
    return make('geometry_msgs/msg/Pose',
                position=make('geometry_msgs/msg/Point', x=float(m[0, 3]), y=float(m[1, 3]),
                              z=float(m[2, 3])),
                orientation=make('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]),
                                 z=float(q[2]), w=float(q[3])))


def pose_stamped_msg(matrix, stamp_ns: int, frame_id: str, make=ROS):
    """geometry_msgs/PoseStamped of a 4x4 pose."""
    return make('geometry_msgs/msg/PoseStamped', header=header(make, stamp_ns, frame_id),
                pose=_pose(make, matrix))


def _covariance36(covariance) -> list:
    """A (6, 6) pose covariance as a message's 36 floats; None: zeros (not estimated)."""
    return [float(v) for v in (np.zeros(36) if covariance is None else np.asarray(covariance, float).reshape(36))]


def pose_with_covariance_msg(matrix, covariance, stamp_ns: int, frame_id: str, make=ROS):
    """geometry_msgs/PoseWithCovarianceStamped of a 4x4 pose and its (6, 6) covariance (x, y,
    z, rotations about x, y, z); None: all zeros (not estimated)."""
    inner = make('geometry_msgs/msg/PoseWithCovariance', pose=_pose(make, matrix), covariance=_covariance36(covariance))
    return make('geometry_msgs/msg/PoseWithCovarianceStamped', header=header(make, stamp_ns, frame_id), pose=inner)


def transform_stamped_msg(matrix, stamp_ns: int, parent: str, child: str, make=ROS):
    """geometry_msgs/TransformStamped: ``matrix`` maps child-frame points into ``parent``."""
    m = np.asarray(matrix, dtype=np.float64)
    q = quaternion_from_matrix(m[:3, :3])
    return make('geometry_msgs/msg/TransformStamped', header=header(make, stamp_ns, parent),
                child_frame_id=child,
                transform=make('geometry_msgs/msg/Transform',
                               translation=_vector3(make, m[:3, 3]),
                               rotation=make('geometry_msgs/msg/Quaternion', x=float(q[0]),
                                             y=float(q[1]), z=float(q[2]), w=float(q[3]))))


def camera_info_msg(intrinsics: CameraIntrinsics, stamp_ns: int, frame_id: str, make=ROS):
    """sensor_msgs/CameraInfo of an undistorted pinhole camera."""
    k = intrinsics.matrix
    p = np.zeros((3, 4))
    p[:, :3] = k
    return make('sensor_msgs/msg/CameraInfo', header=header(make, stamp_ns, frame_id),
                height=int(intrinsics.height), width=int(intrinsics.width),
                distortion_model='plumb_bob', d=np.zeros(5, dtype=np.float64),
                k=k.reshape(-1).astype(np.float64), r=np.eye(3).reshape(-1),
                p=p.reshape(-1), binning_x=0, binning_y=0,
                roi=make('sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0,
                         width=0, do_rectify=False))


def imu_msg(linear_acceleration, angular_velocity, stamp_ns: int, frame_id: str,
            accel_sigma: float = 0.02, gyro_sigma: float = 0.002, make=ROS):
    """sensor_msgs/Imu without orientation (covariance[0] = -1, as drivers without a filter do);
    ``angular_velocity`` None: an accelerometer alone (its covariance[0] = -1 too, REP 145)."""
    orientation_cov = np.zeros(9)
    orientation_cov[0] = -1.0
    gyro_cov = np.eye(3).reshape(-1) * gyro_sigma ** 2
    if angular_velocity is None:
        angular_velocity, gyro_cov = np.zeros(3), orientation_cov.copy()
    return make('sensor_msgs/msg/Imu', header=header(make, stamp_ns, frame_id),
                orientation=make('geometry_msgs/msg/Quaternion', x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=orientation_cov,
                angular_velocity=_vector3(make, angular_velocity),
                angular_velocity_covariance=gyro_cov,
                linear_acceleration=_vector3(make, linear_acceleration),
                linear_acceleration_covariance=np.eye(3).reshape(-1) * accel_sigma ** 2)


def planar_matrix(x: float, y: float, heading: float, z: float = 0.0) -> np.ndarray:
    """4x4 of a planar pose (a heading about z)."""
    m = np.eye(4)
    c, s = np.cos(heading), np.sin(heading)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = (x, y, z)
    return m


def odometry_msg(pose, velocity, stamp_ns: int, frame_id: str = 'odom', child_frame_id: str = 'base_link',
                 sigma_m: float = 0.05, sigma_rad: float = 0.035, make=ROS):
    """nav_msgs/Odometry of a planar base: ``pose`` (x, y, heading) in ``frame_id``,
    ``velocity`` (forward m/s, turn rad/s) in ``child_frame_id``; the covariance of a wheel
    odometry's pose (``sigma_m`` per axis, ``sigma_rad`` in heading; z, roll and pitch fixed)."""
    cov = np.diag([sigma_m ** 2, sigma_m ** 2, 1e-6, 1e-6, 1e-6, sigma_rad ** 2]).reshape(36).astype(np.float64)
    inner = make('geometry_msgs/msg/PoseWithCovariance', pose=_pose(make, planar_matrix(*pose)), covariance=cov)
    twist = make('geometry_msgs/msg/TwistWithCovariance',
                 twist=make('geometry_msgs/msg/Twist', linear=_vector3(make, (velocity[0], 0.0, 0.0)),
                            angular=_vector3(make, (0.0, 0.0, velocity[1]))),
                 covariance=cov.copy())
    return make('nav_msgs/msg/Odometry', header=header(make, stamp_ns, frame_id), child_frame_id=child_frame_id,
                pose=inner, twist=twist)


def box_markers_msg(corners, texts, text_positions, colours, stamp_ns: int, frame_id: str, ids=None,
                    line_width: float = 0.02, text_size: float = 0.1, text_colour=None,
                    namespaces=('boxes', 'labels'), make=ROS):
    """visualization_msgs/MarkerArray drawing boxes for RViz / Foxglove: a DELETEALL, then per
    box a LINE_LIST of its 12 edges and a TEXT_VIEW_FACING label. ``corners`` (N, 8, 3) in
    ``frame_id`` (corner order of rfm_core.geometry), ``texts`` (N,), ``text_positions`` (N, 3),
    ``colours`` (N, 4) RGBA in [0, 1]; ``ids`` (N,) marker ids (default 0..N-1);
    ``text_colour``: one RGBA for every label (default: the box's). Needs ROS (``make``:
    rclpy message objects)."""
    def point(p):
        return make('geometry_msgs/msg/Point', x=float(p[0]), y=float(p[1]), z=float(p[2]))

    def colour(c):
        return make('std_msgs/msg/ColorRGBA', r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]))

    line_list, text_facing, add, delete_all = 5, 9, 0, 3      # visualization_msgs/Marker constants
    head = header(make, stamp_ns, frame_id)
    identity = make('geometry_msgs/msg/Quaternion', x=0.0, y=0.0, z=0.0, w=1.0)
    out = [make('visualization_msgs/msg/Marker', header=head, action=delete_all)]
    corners = np.asarray(corners, float).reshape(-1, 8, 3)
    ids = range(len(corners)) if ids is None else ids
    for c, text, at, rgba, i in zip(corners, texts, text_positions, colours, ids):
        out.append(make('visualization_msgs/msg/Marker', header=head, ns=namespaces[0], id=int(i), type=line_list,
                        action=add, pose=make('geometry_msgs/msg/Pose', orientation=identity),
                        scale=make('geometry_msgs/msg/Vector3', x=float(line_width), y=0.0, z=0.0),
                        color=colour(rgba), points=[point(c[k]) for edge in BOX_EDGES for k in edge]))
        out.append(make('visualization_msgs/msg/Marker', header=head, ns=namespaces[1], id=int(i), type=text_facing,
                        action=add, pose=make('geometry_msgs/msg/Pose', position=point(at), orientation=identity),
                        scale=make('geometry_msgs/msg/Vector3', x=0.0, y=0.0, z=float(text_size)),
                        color=colour(rgba if text_colour is None else text_colour), text=str(text)))
    return make('visualization_msgs/msg/MarkerArray', markers=out)


def object_map_msg(boxes, labels, ids, stamp_ns: int, frame_id: str = 'map', scores=None,
                   revision: int = 0, make=ROS):
    """rfm_msgs/ObjectMap of boxes (N, 7) in ``frame_id`` (a gravity-aligned, z-up frame)."""
    centers, rotations, sizes = oriented_from_boxes(np.asarray(boxes).reshape(-1, 7))
    scores = np.ones(len(centers)) if scores is None else np.asarray(scores)
    objects = []
    for i in range(len(centers)):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rotations[i], centers[i]
        objects.append(make(
            'rfm_msgs/msg/MapObject', id=int(ids[i]), pose=_pose(make, m),
            size=_vector3(make, sizes[i]), score=float(scores[i]), label=labels[i],
            class_names=[labels[i]] if labels[i] else [],
            class_probabilities=make.float32_array([1.0] if labels[i] else []),
            embedding=make.float32_array([]),
            observation_keyframe_ids=np.zeros(0, dtype=np.uint64),
            observation_indices=np.zeros(0, dtype=np.uint32)))
    return make('rfm_msgs/msg/ObjectMap', header=header(make, stamp_ns, frame_id),
                revision=int(revision), objects=objects)


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def ns_to_stamp(ns: int, make=None):
    """Integer nanoseconds -> builtin_interfaces/Time."""
    ns = int(ns)
    return (make or ROS)('builtin_interfaces/msg/Time', sec=ns // _NS, nanosec=ns % _NS)


def vector3_to_numpy(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _quat(q) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=np.float64)


def camera_info_intrinsics(info) -> CameraIntrinsics:
    """sensor_msgs/CameraInfo -> CameraIntrinsics (raises ValueError for zero or bad K)."""
    k = info.k
    return CameraIntrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                            int(info.width), int(info.height))


def imu_reading(msg):
    """sensor_msgs/Imu -> (stamp_ns, specific force (3,), angular velocity (3,) or None when
    the driver marks it unavailable with covariance[0] = -1)."""
    a, w = msg.linear_acceleration, msg.angular_velocity
    gyro = None if msg.angular_velocity_covariance[0] == -1 else [w.x, w.y, w.z]
    return stamp_to_ns(msg.header.stamp), [a.x, a.y, a.z], gyro


def pose_to_matrix(pose) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 matrix. Raises ValueError for a zero or non-finite quaternion."""
    out = np.eye(4)
    out[:3, :3] = matrix_from_quaternion(_quat(pose.orientation))
    out[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    if not np.all(np.isfinite(out)):
        raise ValueError('pose has a non-finite position')
    return out


def matrix_to_pose(matrix, make=ROS):
    """4x4 matrix -> geometry_msgs/Pose."""
    return _pose(make, matrix)


def pose_to_pose4(pose, atol: float = 1e-6) -> Pose4:
    """geometry_msgs/Pose whose rotation is a yaw about z -> Pose4."""
    return Pose4.from_matrix(pose_to_matrix(pose), atol=atol)


def pose4_to_pose(pose4: Pose4, make=ROS):
    """Pose4 -> geometry_msgs/Pose."""
    return _pose(make, pose4.matrix())


def float32_array(values) -> array.array:
    """numpy/sequence -> array.array('f'), the fast way to fill a ROS float32[] field."""
    out = array.array('f')
    out.frombytes(np.ascontiguousarray(values, dtype=np.float32).reshape(-1).tobytes())
    return out


def frame_detections_from_msg(msg) -> FrameObservations:
    """rfm_msgs/FrameDetections -> FrameObservations (boxes in the gravity-aligned frame).

    Validates the message and raises ValueError saying what is wrong: non-positive
    intrinsics or image size, zero gravity, non-finite poses, negative sizes, embeddings of
    different lengths, or non-finite scores, embeddings, corner descriptors or 2D boxes
    (the matchers' assignment and the averaging would fail on them).
    """
    intrinsics = CameraIntrinsics(float(msg.fx), float(msg.fy), float(msg.cx), float(msg.cy),
                                  int(msg.width), int(msg.height))
    gravity = vector3_to_numpy(msg.gravity)
    obs_rotation = gravity_aligned_rotation(gravity)
    dets = list(msg.detections)
    n = len(dets)
    if n > MAX_DETECTIONS:                       # bounded work per message downstream
        raise ValueError(f'{n} detections in one frame; at most {MAX_DETECTIONS} are read')
    boxes = _aligned_boxes(obs_rotation, [d.pose for d in dets], [d.size for d in dets])
    # full boxes (none in messages of older rfm versions): for every detection or for none
    full = [(getattr(d, 'full_pose', ()), getattr(d, 'full_size', ())) for d in dets]
    counts = {(len(p), len(s)) for p, s in full}
    if n and counts != {(0, 0)}:
        if counts != {(1, 1)}:
            raise ValueError('full_pose / full_size must hold one element for every detection or none for all')
    full_boxes = (_aligned_boxes(obs_rotation, [p[0] for p, _ in full], [s[0] for _, s in full])
                  if n and counts == {(1, 1)} else None)
    dims = {len(d.embedding) for d in dets}
    if len(dims) > 1:
        raise ValueError(f'detections have embeddings of different lengths {sorted(dims)}')
    dim = dims.pop() if dims else 0
    if dim > MAX_DESCRIPTOR_DIM or any(len(d.corner_descriptors) > 8 * MAX_DESCRIPTOR_DIM for d in dets):
        raise ValueError(f'embeddings or corner descriptors longer than {MAX_DESCRIPTOR_DIM} values')
    embeddings = (np.array([np.asarray(d.embedding, dtype=np.float32) for d in dets])
                  if n and dim else np.zeros((n, 0), np.float32))
    corner = None
    corner_lengths = {len(d.corner_descriptors) for d in dets}
    if n and corner_lengths != {0}:
        if len(corner_lengths) > 1 or next(iter(corner_lengths)) % 8:
            raise ValueError('corner_descriptors must be 8 x D for every detection or empty for all')
        corner = np.array([np.asarray(d.corner_descriptors, np.float32).reshape(8, -1) for d in dets])
    scores = np.array([d.score for d in dets], dtype=np.float32)
    boxes_2d = np.array([np.asarray(d.box_2d, np.float32) for d in dets]).reshape(n, 4)
    for name, values in (('scores', scores), ('embeddings', embeddings), ('2D boxes', boxes_2d),
                         ('corner descriptors', corner if corner is not None else scores)):
        if not np.all(np.isfinite(values)):
            raise ValueError(f'detection {name} must be finite')
    return FrameObservations(
        stamp_ns=stamp_to_ns(msg.header.stamp),
        frame_id=msg.header.frame_id,
        intrinsics=intrinsics,
        gravity_cam=gravity,
        boxes=boxes,
        scores=scores,
        labels=[d.label for d in dets],
        embeddings=embeddings,
        boxes_2d=boxes_2d,
        visibility=np.array([d.visibility for d in dets], dtype=np.float32),
        object_ids=np.array([d.object_id for d in dets], dtype=np.int64),
        corner_descriptors=corner,
        full_boxes=full_boxes,
        backend=msg.backend,
        # none in messages of older rfm versions; 0, NaN or a non-physical value: not measured
        camera_height=float(getattr(msg, 'camera_height', 0.0)),
        walls=_walls(msg, obs_rotation),
        cloud=_cloud(msg, obs_rotation),
        **_imu_fields(msg), **_odometry_fields(msg),
    )


def _walls(msg, obs_rotation) -> np.ndarray:
    """(W, 3) walls of a FrameDetections in its gravity-aligned frame (none in messages of
    older rfm versions); ValueError for mismatched, non-finite, non-vertical or too many."""
    normals, distances = list(getattr(msg, 'wall_normals', ())), list(getattr(msg, 'wall_distances', ()))
    if len(normals) != len(distances):
        raise ValueError(f'{len(normals)} wall normals for {len(distances)} wall distances')
    if len(normals) > MAX_WALLS:
        raise ValueError(f'{len(normals)} walls in one frame; at most {MAX_WALLS} are read')
    if not normals:
        return np.zeros((0, 3))
    n = np.array([vector3_to_numpy(v) for v in normals]) @ obs_rotation.T      # in the aligned frame
    d = np.asarray(distances, dtype=np.float64)
    norm = np.linalg.norm(n, axis=1)
    if not (np.all(np.isfinite(n)) and np.all(np.isfinite(d))) or np.any(norm < 1e-6):
        raise ValueError('wall normals and distances must be finite, the normals non-zero')
    n /= norm[:, None]
    if np.any(np.abs(n[:, 2]) > np.sin(np.radians(10.0))):
        raise ValueError('wall normals must be perpendicular to gravity (within 10 deg)')
    return np.c_[n[:, :2], d]


def _cloud(msg, obs_rotation) -> np.ndarray:
    """(P, 3) depth points of a FrameDetections in its gravity-aligned frame (none in messages
    of older rfm versions); ValueError for a length that is not x y z triplets, too many
    points or non-finite values."""
    flat = np.asarray(getattr(msg, 'cloud', ()), dtype=np.float32).reshape(-1)
    if flat.size % 3:
        raise ValueError(f'cloud holds {flat.size} values: x y z triplets expected')
    if flat.size > 3 * MAX_CLOUD_POINTS:
        raise ValueError(f'{flat.size // 3} cloud points in one frame; at most {MAX_CLOUD_POINTS} are read')
    if not np.all(np.isfinite(flat)):
        raise ValueError('cloud points must be finite')
    return (flat.reshape(-1, 3) @ obs_rotation.T.astype(np.float32)).astype(np.float32)


def _aligned_boxes(obs_rotation, poses, sizes) -> np.ndarray:
    """(N, 7) gravity-aligned boxes of Pose / Vector3 messages in the camera optical frame;
    ValueError for non-finite or negative sizes."""
    n = len(poses)
    centers, rotations, extents = np.zeros((n, 3)), np.zeros((n, 3, 3)), np.zeros((n, 3))
    for i, (pose, size) in enumerate(zip(poses, sizes)):
        m = pose_to_matrix(pose)
        centers[i] = obs_rotation @ m[:3, 3]
        rotations[i] = obs_rotation @ m[:3, :3]
        extents[i] = vector3_to_numpy(size)
    if not np.all(np.isfinite(extents)) or np.any(extents < 0):
        raise ValueError('detection sizes must be finite and non-negative')
    return boxes_from_oriented(centers, rotations, extents)


def _imu_fields(msg) -> dict:
    """imu_rotation / imu_epoch of a FrameDetections (none in messages of older rfm versions;
    ValueError for a zero or non-finite quaternion with an epoch)."""
    epoch = int(getattr(msg, 'imu_epoch', 0) or 0)
    if not epoch:
        return {}
    q = _quat(msg.imu_orientation)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
        raise ValueError('imu_orientation must be a finite non-zero quaternion')
    return {'imu_rotation': matrix_from_quaternion(q / np.linalg.norm(q)), 'imu_epoch': epoch}


def _odometry_fields(msg) -> dict:
    """odometry / odometry_epoch of a FrameDetections (none in older messages; ValueError for
    a non-finite pose or a zero quaternion with an epoch)."""
    epoch = int(getattr(msg, 'odometry_epoch', 0) or 0)
    if not epoch:
        return {}
    q = _quat(msg.odometry.orientation)
    m = pose_to_matrix(msg.odometry) if np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-6 else None
    if m is None or not np.all(np.isfinite(m)):
        raise ValueError('odometry must be a finite pose with a non-zero quaternion')
    return {'odometry': m, 'odometry_epoch': epoch}


def frame_detections_to_msg(obs: FrameObservations, make=ROS):
    """FrameObservations -> rfm_msgs/FrameDetections (box poses in the camera optical frame)."""
    camera_from_aligned = obs.rotation_aligned_from_camera.T

    def in_camera(boxes):                       # (pose, size) messages in the optical frame
        centers, rotations, sizes = oriented_from_boxes(boxes)
        out = []
        for c, r, s in zip(centers, rotations, sizes):
            m = np.eye(4)
            m[:3, :3] = camera_from_aligned @ r
            m[:3, 3] = camera_from_aligned @ c
            out.append((_pose(make, m), _vector3(make, s)))
        return out

    fitted = in_camera(obs.boxes)
    full = in_camera(obs.full_boxes) if obs.full_boxes is not None else None
    detections = []
    for i in range(len(obs)):
        corner = (obs.corner_descriptors[i] if obs.corner_descriptors is not None else [])
        detections.append(make(
            'rfm_msgs/msg/ObjectDetection', index=i, object_id=int(obs.object_ids[i]),
            pose=fitted[i][0], size=fitted[i][1], score=float(obs.scores[i]),
            full_pose=[full[i][0]] if full else [], full_size=[full[i][1]] if full else [],
            label=obs.labels[i], embedding=make.float32_array(obs.embeddings[i]),
            corner_descriptors=make.float32_array(corner),
            box_2d=np.asarray(obs.boxes_2d[i], dtype=np.float32),
            visibility=float(obs.visibility[i])))
    intr = obs.intrinsics
    return make('rfm_msgs/msg/FrameDetections', header=header(make, obs.stamp_ns, obs.frame_id),
                backend=obs.backend, fx=float(intr.fx), fy=float(intr.fy), cx=float(intr.cx),
                cy=float(intr.cy), width=int(intr.width), height=int(intr.height),
                gravity=_vector3(make, obs.gravity_cam), imu_orientation=_quaternion(make, obs.imu_rotation),
                imu_epoch=int(obs.imu_epoch) if obs.imu_rotation is not None else 0,
                odometry=_pose(make, obs.odometry if obs.odometry is not None else np.eye(4)),
                odometry_epoch=int(obs.odometry_epoch) if obs.odometry is not None else 0,
                camera_height=float(obs.camera_height) if np.isfinite(obs.camera_height) else 0.0,
                wall_normals=[_vector3(make, camera_from_aligned @ np.r_[w[:2], 0.0]) for w in obs.walls],
                wall_distances=np.asarray(obs.walls[:, 2], dtype=np.float64),
                cloud=make.float32_array((obs.cloud @ camera_from_aligned.T.astype(np.float32)).reshape(-1)),
                detections=detections)


def _quaternion(make, rotation):
    q = quaternion_from_matrix(rotation) if rotation is not None else (0.0, 0.0, 0.0, 1.0)
    return make('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def tracked_frame_to_msg(track: FrameTrack, make=ROS, covariance=None):
    """FrameTrack -> rfm_msgs/TrackedFrame; ``covariance``: (16,) over (x, y, z, yaw) of its
    pose (:func:`rfm_core.mapping.uncertainty.tracked_covariance`), None: zeros (not stated)."""
    covariance = np.zeros(16) if covariance is None else np.asarray(covariance, float).reshape(16)
    return make('rfm_msgs/msg/TrackedFrame', header=header(make, track.stamp_ns, track.frame_id),
                keyframe_id=int(track.keyframe_id), keyframe_stamp=ns_to_stamp(track.keyframe_stamp_ns, make),
                yaw=float(track.pose.yaw), translation=_vector3(make, track.pose.t),
                gravity=_vector3(make, track.gravity_cam), num_inliers=int(track.num_inliers),
                is_keyframe=bool(track.is_keyframe), continuous=bool(track.continuous),
                covariance=[float(v) for v in covariance])


def tracked_frame_from_msg(msg) -> FrameTrack:
    """rfm_msgs/TrackedFrame -> FrameTrack; ValueError when malformed (non-finite pose,
    zero gravity)."""
    t = vector3_to_numpy(msg.translation)
    if not (np.isfinite(msg.yaw) and np.all(np.isfinite(t))):
        raise ValueError('tracked frame pose is not finite')
    return FrameTrack(stamp_to_ns(msg.header.stamp), msg.header.frame_id, vector3_to_numpy(msg.gravity),
                      int(msg.keyframe_id), stamp_to_ns(msg.keyframe_stamp), Pose4(float(msg.yaw), t),
                      int(msg.num_inliers), bool(msg.is_keyframe), bool(msg.continuous))


def edge_msg(edge, stamp_ns: int, make=ROS):
    """A view-graph edge (:class:`rfm_core.matching.view_graph.Edge`) -> rfm_msgs/ViewGraphEdge:
    T_source_target, the inlier object and corner matches, the verification score."""
    rel = edge.relative
    return make('rfm_msgs/msg/ViewGraphEdge', header=header(make, stamp_ns, ''),
                source_id=int(edge.source_id), target_id=int(edge.target_id), yaw=float(rel.pose.yaw),
                translation=_vector3(make, rel.pose.t), num_matches=int(rel.num_matches),
                inliers=[make('rfm_msgs/msg/ObjectMatch', source_index=int(s), target_index=int(t), score=float(sc),
                              iou=float(iou))
                         for (s, t), sc, iou in zip(rel.inliers, rel.inlier_scores, rel.inlier_ious)],
                corner_inliers=[make('rfm_msgs/msg/CornerMatch', source_index=int(s), source_corner=int(cs),
                                     target_index=int(t), target_corner=int(ct), error=float(e))
                                for s, cs, t, ct, e in rel.corner_inliers],
                mean_error=float(rel.mean_error), score=edge.score)


def edge_record_from_msg(msg):
    """rfm_msgs/ViewGraphEdge -> :class:`rfm_core.observations.EdgeRecord`; ValueError when
    malformed (a non-finite pose). A score outside [0, 1] is clipped, a non-finite one is 0."""
    t = vector3_to_numpy(msg.translation)
    if not (np.isfinite(msg.yaw) and np.all(np.isfinite(t))):
        raise ValueError('edge pose is not finite')
    inliers = np.array([[m.source_index, m.target_index] for m in msg.inliers], np.int64).reshape(-1, 2)
    corners = np.array([[c.source_index, c.source_corner, c.target_index, c.target_corner, c.error]
                        for c in msg.corner_inliers], float).reshape(-1, 5)
    return EdgeRecord(int(msg.source_id), int(msg.target_id), Pose4(float(msg.yaw), t), inliers,
                      np.array([m.score for m in msg.inliers], np.float32), corners,
                      float(np.clip(msg.score, 0.0, 1.0)) if np.isfinite(msg.score) else 0.0)


def transform_to_matrix(transform) -> np.ndarray:
    """geometry_msgs/Transform -> 4x4."""
    m = np.eye(4)
    m[:3, :3] = matrix_from_quaternion(_quat(transform.rotation))
    m[:3, 3] = vector3_to_numpy(transform.translation)
    return m


def track_colour(track_id: int) -> tuple:
    """A stable, distinct display colour per track, (r, g, b) in [0, 1]: a golden-ratio walk
    around the hue circle at full saturation."""
    h = (track_id * 0.618033988749895) % 1.0
    k = int(h * 6)
    f = h * 6 - k
    return [(1, f, 0), (1 - f, 1, 0), (0, 1, f), (0, 1 - f, 1), (f, 0, 1), (1, 0, 1 - f)][k % 6]


def track_map_msgs(tracks, stamp_ns: int, frame_id: str, revision: int = 0, make=ROS) -> tuple:
    """The mapper's object tracks (:class:`rfm_core.mapping.tracks.Track`) as the
    rfm_msgs/ObjectMap it publishes (class distributions, embeddings, observations) and the
    MarkerArray drawing them, each track in its own colour, labelled with class, score and
    number of views."""
    boxes = np.array([t.box for t in tracks]).reshape(-1, 7)
    msg = object_map_msg(boxes, [t.label for t in tracks], [t.track_id for t in tracks], stamp_ns, frame_id,
                         scores=[t.score for t in tracks], revision=revision, make=make)
    for obj, t in zip(msg.objects, tracks):
        names = sorted(t.class_distribution)
        obj.class_names = names
        obj.class_probabilities = [float(t.class_distribution[n]) for n in names]
        obj.embedding = [float(v) for v in t.embedding]
        obj.observation_keyframe_ids = [int(k) for k in t.observations[:, 0]]
        obj.observation_indices = [int(i) for i in t.observations[:, 1]]
    colours = [tuple(0.3 + 0.7 * c for c in track_colour(t.track_id)) + (1.0,) for t in tracks]   # lightened
    markers = box_markers_msg(
        box_corners(boxes).reshape(-1, 8, 3),
        [f'{t.label or "object"} {t.score:.2f} ({t.num_observations})' for t in tracks],
        boxes[:, :3] + np.c_[np.zeros((len(boxes), 2)), boxes[:, 5] / 2 + 0.08],
        colours, stamp_ns, frame_id, ids=[int(t.track_id % 2**31) for t in tracks], make=make)
    return msg, markers


# The mapper's outputs as [(topic, message)]: the node publishes each on its topic.

def keyframe_pose_outputs(ids, poses: dict, stamps: dict, frame_id: str, make=ROS) -> list:
    """rfm/keyframe_poses (geometry_msgs/PoseArray) and rfm/trajectory (nav_msgs/Path) of
    keyframes' camera-to-map poses (``ids`` in order, ``poses`` {id: 4x4}, ``stamps`` {id:
    stamp_ns}), stamped with the newest; [] without keyframes."""
    if not len(ids):
        return []
    stamp = header(make, stamps[ids[-1]], frame_id)
    array = make('geometry_msgs/msg/PoseArray', header=stamp, poses=[_pose(make, poses[k]) for k in ids])
    path = make('nav_msgs/msg/Path', header=stamp,
                poses=[pose_stamped_msg(poses[k], stamps[k], frame_id, make) for k in ids])
    return [('rfm/keyframe_poses', array), ('rfm/trajectory', path)]


def camera_pose_outputs(camera, frame_id: str, attachment=None, make=ROS) -> list:
    """rfm/camera_pose (geometry_msgs/PoseWithCovarianceStamped) of a localized frame
    (:class:`rfm_core.session.CameraPose`), and /tf where the map attaches to the TF tree
    (``attachment``: :class:`rfm_core.transforms.Attachment`, stamped with the image); [] for None."""
    if camera is None:
        return []
    out = [('rfm/camera_pose', pose_with_covariance_msg(camera.matrix, camera.covariance, camera.stamp_ns, frame_id,
                                                         make))]
    if attachment is not None:
        out.append(('/tf', attachment_msg(attachment, attachment.stamp_ns or camera.stamp_ns, frame_id, make)))
    return out


def transforms_from_msg(msg) -> list:
    """tf2_msgs/TFMessage -> [(parent, child, stamp_ns, 4x4 T_parent_child)]; ValueError when
    a transform is not finite."""
    out = []
    for t in msg.transforms:
        matrix = transform_to_matrix(t.transform)
        if not np.all(np.isfinite(matrix)):
            raise ValueError(f'transform {t.header.frame_id} -> {t.child_frame_id} is not finite')
        out.append((t.header.frame_id, t.child_frame_id, stamp_to_ns(t.header.stamp), matrix))
    return out


def attachment_msg(attachment, stamp_ns: int, frame_id: str, make=ROS):
    """tf2_msgs/TFMessage of the map frame -> the frame the map attaches to."""
    return make('tf2_msgs/msg/TFMessage', transforms=[
        transform_stamped_msg(attachment.matrix, stamp_ns, frame_id, attachment.child, make)])


def object_map_outputs(tracks, stamp_ns: int, revision: int, frame_id: str, make=ROS) -> list:
    """rfm/object_map and rfm/object_markers of the map's tracks (:func:`track_map_msgs`)."""
    objects, markers = track_map_msgs(tracks, stamp_ns, frame_id, revision, make)
    return [('rfm/object_map', objects), ('rfm/object_markers', markers)]


def tick_outputs(tick, frame_id: str, attachment=None, make=ROS) -> list:
    """What a :class:`rfm_core.mapper_core.Tick` publishes: keyframe poses and trajectory, the
    newest camera pose (and /tf, ``attachment``), the object map and its markers."""
    out = keyframe_pose_outputs(*tick.keyframe_poses, frame_id, make) if tick.keyframe_poses else []
    out += camera_pose_outputs(tick.camera, frame_id, attachment, make)
    return out + (object_map_outputs(*tick.object_map, frame_id, make) if tick.object_map else [])


def mapper_status_msg(status, stamp_ns: int, frame_id: str, make=ROS):
    """rfm_msgs/MapperStatus of a :class:`rfm_core.mapper_core.MapStatus` (the same fields;
    counts saturate at the message's uint32: hostile sequence numbers can claim 2^64 lost)."""
    fields = {k: min(max(v, 0), 2 ** 32 - 1) if isinstance(v, int) and not isinstance(v, bool) else v
              for k, v in vars(status).items()}
    fields['mode'] = 1 if fields['mode'] == 'localization' else 0          # MODE_LOCALIZATION / MODE_MAPPING
    return make('rfm_msgs/msg/MapperStatus', header=header(make, stamp_ns, frame_id), **fields)


def relocalize_answer(query, relocalize, frame_id: str, make=ROS) -> dict:
    """rfm_msgs/Relocalize's response fields for a query message: decoded (a malformed one is
    refused with the reason), ``relocalize(obs)`` -> (Relocalization or None, message), the
    pose as a PoseStamped in ``frame_id`` and its covariance (zeros: not estimated)."""
    try:
        obs = frame_detections_from_msg(query)
    except ValueError as exc:
        return dict(success=False, message=f'bad query: {exc}')
    reloc, message = relocalize(obs)
    if reloc is None:
        return dict(success=False, message=message)
    return dict(success=True, message=message, num_inliers=int(reloc.num_inliers),
                keyframe_id=int(reloc.keyframe_id),
                pose=pose_stamped_msg(reloc.camera_to_map(obs), obs.stamp_ns, frame_id, make),
                covariance=_covariance36(reloc.covariance))


def detection_markers_msg(obs: FrameObservations, make=ROS):
    """visualization_msgs/MarkerArray of a frame's boxes in its camera optical frame, coloured
    by score (red to green) and labelled with class and score."""
    corners = box_corners(obs.boxes).reshape(-1, 8, 3) @ obs.rotation_aligned_from_camera    # aligned -> camera
    scores = np.asarray(obs.scores, float)
    return box_markers_msg(
        corners, [f'{label + " " if label else ""}{score:.2f}' for label, score in zip(obs.labels, scores)],
        corners[:, 4:].mean(1), np.stack([1.0 - scores, scores, np.full_like(scores, 0.2), np.ones_like(scores)], 1),
        obs.stamp_ns, obs.frame_id, line_width=0.01, text_size=0.08, text_colour=(1.0, 1.0, 1.0, 1.0),
        namespaces=('boxes', 'scores'), make=make)


def diagnostics_msg(name: str, hardware_id: str, warn: bool, message: str, values: dict, stamp_ns: int, make=ROS):
    """diagnostic_msgs/DiagnosticArray of one status (OK, or WARN) with key-value pairs."""
    status = make('diagnostic_msgs/msg/DiagnosticStatus', level=bytes([1 if warn else 0]), name=name,
                  message=message, hardware_id=hardware_id,
                  values=[make('diagnostic_msgs/msg/KeyValue', key=k, value=str(v)) for k, v in values.items()])
    return make('diagnostic_msgs/msg/DiagnosticArray', header=header(make, stamp_ns, ''), status=[status])
