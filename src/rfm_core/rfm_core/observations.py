"""ROS-free data types exchanged between the stages (mirrors of the rfm_msgs messages)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from rfm_core.clouds import PointIndex
from rfm_core.geometry import BOX_DIM, Pose4, gravity_aligned_rotation

__all__ = ['CameraIntrinsics', 'FrameObservations', 'FrameTrack', 'EdgeRecord']


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics (pixels) of an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(values)) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f'intrinsics need finite fx, fy > 0 (got fx={self.fx}, fy={self.fy}, '
                             f'cx={self.cx}, cy={self.cy}); is camera_info calibrated?')
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f'image size must be positive, got {self.width}x{self.height}')

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def unit_gravity(gravity) -> np.ndarray:
    """Gravity as a unit 3-vector; ValueError unless finite and non-zero."""
    g = np.asarray(gravity, dtype=np.float64).reshape(-1)
    norm = np.linalg.norm(g) if g.size == 3 else 0.0
    if g.size != 3 or not np.isfinite(norm) or norm < 1e-6:
        raise ValueError(f'gravity must be a finite non-zero 3-vector, got {gravity!r}')
    return g / norm


def imu_relative_yaw(a, b) -> float | None:
    """Yaw (rad) of T_a_b, between two frames' gravity-aligned camera frames, as the
    gyroscope measured it (their ``imu_rotation``), or None when they share no integration
    epoch. ``a``, ``b``: FrameObservations."""
    if not a.imu_epoch or a.imu_epoch != b.imu_epoch or a.imu_rotation is None or b.imu_rotation is None:
        return None
    delta = a.imu_rotation.T @ b.imu_rotation                    # camera b -> camera a
    m = a.rotation_aligned_from_camera @ delta @ b.rotation_aligned_from_camera.T
    return float(np.arctan2(m[1, 0], m[0, 0]))


def _empty_f32(*shape):
    return np.zeros(shape, dtype=np.float32)


@dataclass
class FrameObservations:
    """The detections of one image (rfm_msgs/FrameDetections without ROS types).

    ``boxes`` (N, 7) and ``scores`` (N,) are required; the other per-box fields may be left
    empty (unknown). ``boxes`` are in the frame's gravity-aligned camera frame
    (:func:`rfm_core.geometry.gravity_aligned_rotation` of ``gravity_cam``), so they have a
    yaw only; ``gravity_cam`` is the unit "down" direction in the camera optical frame.
    """

    stamp_ns: int
    frame_id: str
    intrinsics: CameraIntrinsics
    gravity_cam: np.ndarray
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, BOX_DIM)))
    scores: np.ndarray = field(default_factory=lambda: _empty_f32(0))
    labels: list = field(default_factory=list)
    embeddings: np.ndarray = field(default_factory=lambda: _empty_f32(0, 0))
    boxes_2d: np.ndarray = field(default_factory=lambda: _empty_f32(0, 4))
    visibility: np.ndarray = field(default_factory=lambda: _empty_f32(0))
    object_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    corner_descriptors: np.ndarray | None = None   #: (N, 8, D) or None
    #: (N, 7) the detector's estimate of each object's full box where it differs from
    #: ``boxes`` (depth_clusters' box refiner: ``boxes`` fit the visible points and repeat
    #: from view to view, for relative poses; these complete the object, for the map); None:
    #: ``boxes`` are the full boxes
    full_boxes: np.ndarray | None = None
    backend: str = ''
    imu_rotation: np.ndarray | None = None   #: (3, 3) camera -> the gyroscope's drifting frame
    imu_epoch: int = 0                       #: 0: none; rotations compare within one epoch
    #: (4, 4) the camera optical frame in a robot's odometry frame at the stamp (its wheel
    #: odometry through its TF tree): drifts with distance, exact between close frames
    odometry: np.ndarray | None = None
    odometry_epoch: int = 0                  #: 0: none; poses compare within one epoch
    #: height of the camera above the floor along gravity (m), where the detector measured the
    #: floor plane; NaN: not measured
    camera_height: float = float('nan')
    #: (W, 3) vertical planes (walls) the detector measured: unit horizontal normal (nx, ny)
    #: in the gravity-aligned camera frame, pointing away from the camera, and the plane's
    #: distance d > 0 (points p on it: n . p_xy = d); empty: none measured
    walls: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: (P, 3) float32 depth points of the frame, voxel-downsampled, in the gravity-aligned
    #: camera frame (:func:`rfm_core.clouds.depth_cloud`); empty: none (no depth)
    cloud: np.ndarray = field(default_factory=lambda: _empty_f32(0, 3))
    _point_index: object = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.gravity_cam = unit_gravity(self.gravity_cam)
        self.boxes = np.asarray(self.boxes, dtype=np.float64).reshape(-1, BOX_DIM)
        n = len(self.boxes)
        if not np.all(np.isfinite(self.boxes)):
            raise ValueError('boxes contain NaN or inf')
        if np.any(self.boxes[:, 3:6] < 0):
            raise ValueError('box sizes must be non-negative')
        self.scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)
        self.embeddings = np.asarray(self.embeddings, dtype=np.float32)
        if self.embeddings.size == 0:
            self.embeddings = self.embeddings.reshape(n, 0)
        self.boxes_2d = np.asarray(self.boxes_2d, dtype=np.float32).reshape(-1, 4)
        self.visibility = np.asarray(self.visibility, dtype=np.float32).reshape(-1)
        self.object_ids = np.asarray(self.object_ids, dtype=np.int64).reshape(-1)
        self.labels = list(self.labels)
        # Optional per-box fields may be left empty: fill them with "unknown".
        if n and not self.labels:
            self.labels = [''] * n
        if n and self.embeddings.shape[0] == 0:
            self.embeddings = _empty_f32(n, 0)
        if n and len(self.boxes_2d) == 0:
            self.boxes_2d = _empty_f32(n, 4)
        if n and len(self.visibility) == 0:
            self.visibility = np.full(n, -1.0, dtype=np.float32)
        if n and len(self.object_ids) == 0:
            self.object_ids = np.full(n, -1, dtype=np.int64)
        for name, value in (('scores', self.scores), ('labels', self.labels),
                            ('embeddings', self.embeddings), ('boxes_2d', self.boxes_2d),
                            ('visibility', self.visibility), ('object_ids', self.object_ids)):
            if len(value) != n:
                raise ValueError(f'{name} has {len(value)} entries for {n} boxes')
        if self.embeddings.ndim != 2:
            raise ValueError(f'embeddings must be (N, D), got shape {self.embeddings.shape}')
        if self.imu_rotation is not None:
            r = np.asarray(self.imu_rotation, dtype=np.float64)
            if r.shape != (3, 3) or not np.all(np.isfinite(r)) or not np.allclose(r @ r.T, np.eye(3), atol=1e-4):
                raise ValueError('imu_rotation must be a finite 3x3 rotation')
            self.imu_rotation = r
        elif self.imu_epoch:
            raise ValueError('imu_epoch is set without an imu_rotation')
        self.camera_height = float(self.camera_height)
        if not (np.isnan(self.camera_height) or (np.isfinite(self.camera_height) and self.camera_height > 0)):
            self.camera_height = float('nan')         # 0 / inf / negative: not a measurement
        walls = np.array(self.walls, dtype=np.float64)          # (a copy: normalised below)
        if walls.size == 0:
            walls = walls.reshape(0, 3)
        if walls.ndim != 2 or walls.shape[1] != 3 or not np.all(np.isfinite(walls)):
            raise ValueError(f'walls must be finite (W, 3) rows (nx, ny, d), got shape {walls.shape}')
        norm = np.hypot(walls[:, 0], walls[:, 1])
        if np.any(norm < 0.5) or np.any(walls[:, 2] <= 0):
            raise ValueError('walls need a horizontal normal of unit length and a positive distance')
        walls[:, :2] /= norm[:, None]
        self.walls = walls
        cloud = np.asarray(self.cloud, dtype=np.float32)
        if cloud.size == 0:
            cloud = cloud.reshape(0, 3)
        if cloud.ndim != 2 or cloud.shape[1] != 3 or not np.all(np.isfinite(cloud)):
            raise ValueError(f'cloud must be finite (P, 3) points, got shape {cloud.shape}')
        self.cloud = cloud
        if self.corner_descriptors is not None:
            cd = np.asarray(self.corner_descriptors, dtype=np.float32)
            if cd.ndim != 3 or cd.shape[:2] != (n, 8):
                raise ValueError(f'corner_descriptors must be (N, 8, D), got {cd.shape}')
            self.corner_descriptors = cd
        if self.full_boxes is not None:
            fb = np.asarray(self.full_boxes, dtype=np.float64)
            if fb.shape != (n, BOX_DIM) or not np.all(np.isfinite(fb)) or np.any(fb[:, 3:6] < 0):
                raise ValueError(f'full_boxes must be finite ({n}, {BOX_DIM}) boxes with non-negative sizes, '
                                 f'got shape {fb.shape}')
            self.full_boxes = fb

    def subset(self, idx) -> 'FrameObservations':
        """The same frame with detections ``idx`` only (indices or a boolean mask), every
        per-detection field with them."""
        idx = np.flatnonzero(idx) if np.asarray(idx).dtype == bool else np.asarray(idx, dtype=np.int64).reshape(-1)
        return replace(self, boxes=self.boxes[idx], scores=self.scores[idx], labels=[self.labels[i] for i in idx],
                       embeddings=self.embeddings[idx], boxes_2d=self.boxes_2d[idx], visibility=self.visibility[idx],
                       object_ids=self.object_ids[idx],
                       corner_descriptors=None if self.corner_descriptors is None else self.corner_descriptors[idx],
                       full_boxes=None if self.full_boxes is None else self.full_boxes[idx])

    def point_index(self):
        """The cloud ready to be aligned to (:class:`rfm_core.clouds.PointIndex`),
        built once per cloud."""
        if self._point_index is None or self._point_index.cloud is not self.cloud:
            self._point_index = PointIndex(self.cloud)
        return self._point_index

    @property
    def map_boxes(self) -> np.ndarray:
        """(N, 7) the boxes the map is built from: ``full_boxes`` where given, else ``boxes``."""
        return self.boxes if self.full_boxes is None else self.full_boxes

    def __len__(self) -> int:
        return len(self.boxes)

    @property
    def rotation_aligned_from_camera(self) -> np.ndarray:
        """R (3, 3) with p_aligned = R p_camera (see gravity_aligned_rotation)."""
        return gravity_aligned_rotation(self.gravity_cam)


@dataclass
class FrameTrack:
    """A processed frame localized against a keyframe (rfm_msgs/TrackedFrame): ``pose`` is
    T_keyframe_frame between their gravity-aligned camera frames. A keyframe is its own
    reference (its id, the identity pose). The frame's camera pose in the map is the
    keyframe's pose composed with ``pose`` and the frame's gravity."""

    stamp_ns: int
    frame_id: str
    gravity_cam: np.ndarray                 #: unit "down" in the camera optical frame
    keyframe_id: int
    keyframe_stamp_ns: int                  #: the keyframe's stamp (tells a reused id apart)
    pose: Pose4                             #: T_keyframe_frame
    num_inliers: int = 0                    #: verified object matches behind ``pose``
    is_keyframe: bool = False
    continuous: bool = True                 #: part of a stream the matcher followed (motion prior on)

    def __post_init__(self):
        self.gravity_cam = unit_gravity(self.gravity_cam)
        if not (np.isfinite(self.pose.yaw) and np.all(np.isfinite(self.pose.t))):
            raise ValueError('frame pose is not finite')

    @property
    def rotation_aligned_from_camera(self) -> np.ndarray:
        """R (3, 3) with p_aligned = R p_camera (see gravity_aligned_rotation)."""
        return gravity_aligned_rotation(self.gravity_cam)


@dataclass
class EdgeRecord:
    """A verified edge of the view graph as the mapper keeps it (rfm_msgs/ViewGraphEdge)."""

    source: int
    target: int
    pose: Pose4                              #: T_source_target
    inliers: np.ndarray                      #: (K, 2) detection indices (source, target)
    scores: np.ndarray                       #: (K,) match scores
    corner_inliers: np.ndarray               #: (C, 5) source idx, corner, target idx, corner, error
    score: float = 1.0

    @property
    def weight(self) -> float:
        """Averaging weight: more verified objects, more trust."""
        return float(max(len(self.inliers), 1)) * max(self.score, 1e-3)

    @classmethod
    def from_edge(cls, edge) -> 'EdgeRecord':
        """From a view-graph edge (:class:`rfm_core.matching.view_graph.Edge`)."""
        rel = edge.relative
        return cls(edge.source_id, edge.target_id, rel.pose, rel.inliers, rel.inlier_scores,
                   np.asarray(rel.corner_inliers, float).reshape(-1, 5), edge.score)
