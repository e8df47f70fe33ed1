"""Gravity-aligned 3D boxes, 4-DoF transforms, Kabsch-4DoF and oriented 3D IoU.

Rooms from Motion works in *gravity-aligned* frames: roll and pitch are known from gravity,
so boxes have a yaw only and relative poses are 4-DoF (yaw + translation), paper 3.4.

Frames
------
- Camera optical frame (REP-103): x right, y down, z forward. Detections arrive in it.
- Gravity-aligned camera frame (:func:`gravity_aligned_rotation`): origin at the camera
  center, z up (against gravity), x the viewing direction projected onto the horizontal
  plane, y = z x x (left). Boxes, matching and relative poses live in it.
- Map frame: gravity-aligned, z up; keyframe poses are 4-DoF transforms into it.

Boxes
-----
A box array has shape ``(..., 7)``: ``[cx, cy, cz, sx, sy, sz, yaw]`` in metres and
radians. ``(cx, cy, cz)`` is the center, ``(sx, sy, sz)`` the full extents along the box's
local x, y and vertical z axis, and ``yaw`` the rotation of the local x axis about +z.

Corner order (``box_corners``), in box-local axes::

        7 -------- 6
       /|         /|        z (up)
      4 -------- 5 |        |   y
      | |        | |        |  /
      | 3 -------|-2        | /
      |/         |/         +------ x
      0 -------- 1

Corners 0-3 are the bottom face, counter-clockwise seen from above, starting at
(-sx/2, -sy/2); corner i + 4 is straight above corner i.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    'BOX_DIM', 'CORNER_SIGNS', 'BOX_EDGES', 'Pose4', 'wrap_angle', 'circular_mean', 'yaw_matrix', 'box_corners',
    'bev_corners', 'box_volume', 'boxes_from_oriented', 'oriented_from_boxes',
    'gravity_from_accelerometer', 'gravity_aligned_rotation', 'quaternion_from_matrix',
    'matrix_from_quaternion', 'kabsch_4dof', 'kabsch_4dof_batch', 'ray_covariances',
    'align_4dof_anisotropic', 'convex_hull_area', 'iou_3d', 'iou_3d_paired', 'giou_3d', 'giou_3d_paired',
]

BOX_DIM = 7

#: Signs of the corners in box-local axes, in the documented corner order; shape (8, 3).
CORNER_SIGNS = np.array([
    [-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
    [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1],
], dtype=np.float64)

#: The 12 edges of a box as corner index pairs (corner order above); shape (12, 2).
BOX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])

# Distances below this (m) are "the same point" for polygon clipping and hulls.
_LENGTH_TOL = 1e-9


def wrap_angle(angle):
    """Wrap angles (rad) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def circular_mean(angles, weights) -> float:
    """Weighted mean of angles (rad)."""
    w = np.asarray(weights, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    return float(np.arctan2(np.sum(w * np.sin(a)), np.sum(w * np.cos(a))))


def yaw_matrix(yaw):
    """Rotation matrices about +z; ``yaw`` of shape (...,) gives (..., 3, 3)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros(yaw.shape + (3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


def _as_boxes(boxes) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.shape[-1] != BOX_DIM:
        raise ValueError(f'boxes must have shape (..., 7) [cx, cy, cz, sx, sy, sz, yaw], got {boxes.shape}')
    return boxes


def box_corners(boxes) -> np.ndarray:
    """Corners of boxes (..., 7) as (..., 8, 3), in the documented corner order."""
    boxes = _as_boxes(boxes)
    local = 0.5 * boxes[..., None, 3:6] * CORNER_SIGNS
    return np.einsum('...ij,...kj->...ki', yaw_matrix(boxes[..., 6]), local) + boxes[..., None, :3]


def bev_corners(boxes) -> np.ndarray:
    """Footprints (bird's-eye view) of boxes (..., 7) as counter-clockwise (..., 4, 2)."""
    return box_corners(boxes)[..., :4, :2]


def box_volume(boxes) -> np.ndarray:
    """Volumes (m^3) of boxes (..., 7)."""
    boxes = _as_boxes(boxes)
    return np.prod(boxes[..., 3:6], axis=-1)


def boxes_from_oriented(centers, rotations, sizes) -> np.ndarray:
    """Gravity-aligned boxes (N, 7) from oriented boxes in a gravity-aligned (z up) frame.

    ``rotations`` (N, 3, 3) map box-local axes to the frame. The box axis closest to the
    vertical becomes the box's z axis (so detectors with other axis conventions work); the
    first of the remaining axes, in cyclic order, becomes x and defines the yaw. Any tilt of
    the vertical axis is dropped: the box is projected to the nearest gravity-aligned one.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    n = len(centers)
    vertical = np.argmax(np.abs(rotations[:, 2, :]), axis=1)
    x_axis = (vertical + 1) % 3
    y_axis = (vertical + 2) % 3
    rows = np.arange(n)
    x_dir = rotations[rows, :, x_axis]
    yaw = np.arctan2(x_dir[:, 1], x_dir[:, 0])
    out = np.empty((n, BOX_DIM))
    out[:, :3] = centers
    out[:, 3] = sizes[rows, x_axis]
    out[:, 4] = sizes[rows, y_axis]
    out[:, 5] = sizes[rows, vertical]
    out[:, 6] = wrap_angle(yaw)
    return out


def oriented_from_boxes(boxes):
    """(centers (N, 3), rotations (N, 3, 3), sizes (N, 3)) of boxes (N, 7)."""
    boxes = _as_boxes(boxes).reshape(-1, BOX_DIM)
    return boxes[:, :3].copy(), yaw_matrix(boxes[:, 6]), boxes[:, 3:6].copy()


# --------------------------------------------------------------------------------------
# Gravity


def gravity_from_accelerometer(specific_force) -> np.ndarray:
    """Unit gravity ("down") from an accelerometer reading at rest.

    An accelerometer at rest measures the specific force, +9.81 m/s^2 along "up"; gravity
    points the opposite way. Input and output are in the same (sensor) frame.
    """
    f = np.asarray(specific_force, dtype=np.float64)
    norm = np.linalg.norm(f)
    if not np.isfinite(norm) or norm < 1e-6:
        raise ValueError(f'accelerometer reading {f} has no usable direction')
    return -f / norm


def gravity_aligned_rotation(gravity_cam) -> np.ndarray:
    """Rotation R (3, 3) from the camera optical frame to its gravity-aligned frame.

    ``gravity_cam`` is the gravity ("down") direction in the camera optical frame (any
    length). The gravity-aligned frame has z up, x along the viewing direction projected on
    the horizontal plane (the image "up" direction when looking straight up or down), and
    y = z x x. ``p_aligned = R @ p_camera``.
    """
    g = np.asarray(gravity_cam, dtype=np.float64)
    norm = np.linalg.norm(g)
    if g.shape != (3,) or not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f'gravity must be a finite non-zero 3-vector, got {gravity_cam!r}')
    up = -g / norm
    forward = np.array([0.0, 0.0, 1.0])
    x = forward - forward.dot(up) * up
    if np.linalg.norm(x) < 1e-3:          # looking straight up or down
        image_up = np.array([0.0, -1.0, 0.0])
        x = image_up - image_up.dot(up) * up
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    return np.stack([x, y, up])


# --------------------------------------------------------------------------------------
# Quaternions (ROS order: x, y, z, w)


def quaternion_from_matrix(rotation) -> np.ndarray:
    """Unit quaternion(s) (..., 4) as (x, y, z, w), w >= 0, from rotation matrices (..., 3, 3)."""
    m = np.asarray(rotation, dtype=np.float64)
    batch = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Shepperd's method: pick the numerically largest of 4w^2, 4x^2, 4y^2, 4z^2.
    cands = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    which = np.argmax(cands, axis=1)
    q = np.empty((len(m), 4))
    for k in range(4):
        sel = which == k
        if not np.any(sel):
            continue
        r = m[sel]
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr[sel])
            q[sel] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                               (r[:, 1, 0] - r[:, 0, 1]) / s, 0.25 * s], axis=1)
        else:
            i = k - 1
            j, k2 = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(np.maximum(1.0 + r[:, i, i] - r[:, j, j] - r[:, k2, k2], 0.0))
            qq = np.empty((len(r), 4))
            qq[:, i] = 0.25 * s
            qq[:, j] = (r[:, j, i] + r[:, i, j]) / s
            qq[:, k2] = (r[:, k2, i] + r[:, i, k2]) / s
            qq[:, 3] = (r[:, k2, j] - r[:, j, k2]) / s
            q[sel] = qq
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(batch + (4,))


def matrix_from_quaternion(quaternion) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) as (x, y, z, w); normalises."""
    q = np.asarray(quaternion, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(norm)) or np.any(norm < 1e-9):
        raise ValueError('quaternion must be finite and non-zero')
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


# --------------------------------------------------------------------------------------
# 4-DoF transforms


@dataclass(frozen=True)
class Pose4:
    """A 4-DoF rigid transform between gravity-aligned frames: p_a = Rz(yaw) p_b + t.

    Read ``T_a_b``: it maps points from frame b into frame a. Compose with ``@``:
    ``T_a_c = T_a_b @ T_b_c``.
    """

    yaw: float = 0.0                      #: rad
    translation: tuple = (0.0, 0.0, 0.0)  #: m, (x, y, z)

    def __post_init__(self):
        t = tuple(float(v) for v in np.asarray(self.translation, dtype=np.float64).reshape(3))
        object.__setattr__(self, 'translation', t)
        object.__setattr__(self, 'yaw', float(wrap_angle(float(self.yaw))))

    @property
    def t(self) -> np.ndarray:
        """Translation as a (3,) array (m)."""
        return np.array(self.translation)

    @property
    def rotation(self) -> np.ndarray:
        """Rotation matrix (3, 3)."""
        return yaw_matrix(self.yaw)

    def matrix(self) -> np.ndarray:
        """Homogeneous 4x4 matrix."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    @classmethod
    def from_matrix(cls, matrix, atol: float = 1e-6) -> 'Pose4':
        """From a 4x4 (or 3x4) transform whose rotation is about z only (within ``atol``)."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f'expected a 4x4 or 3x4 matrix, got shape {m.shape}')
        yaw = np.arctan2(m[1, 0], m[0, 0])
        if not np.allclose(m[:3, :3], yaw_matrix(yaw), atol=atol):
            raise ValueError('rotation is not a pure yaw about +z: roll/pitch must be removed '
                             'by gravity alignment before using a 4-DoF pose')
        return cls(yaw, m[:3, 3])

    def quaternion(self) -> np.ndarray:
        """Rotation as a quaternion (x, y, z, w)."""
        return np.array([0.0, 0.0, np.sin(self.yaw / 2.0), np.cos(self.yaw / 2.0)])

    @classmethod
    def from_quaternion(cls, quaternion, translation=(0.0, 0.0, 0.0), atol: float = 1e-6) -> 'Pose4':
        """From a quaternion (x, y, z, w) about z only (within ``atol``) and a translation."""
        m = np.eye(4)
        m[:3, :3] = matrix_from_quaternion(quaternion)
        m[:3, 3] = translation
        return cls.from_matrix(m, atol=atol)

    @classmethod
    def from_centre(cls, yaw: float, centre) -> 'Pose4':
        """``T_k_map`` of a frame with heading ``yaw`` whose origin is at ``centre`` in the map
        (the parametrisation pose averaging solves for): ``t = -Rz(yaw) centre``."""
        return cls(yaw, -(yaw_matrix(float(wrap_angle(float(yaw)))) @ np.asarray(centre, dtype=np.float64)))

    def inverse(self) -> 'Pose4':
        return Pose4(-self.yaw, -(yaw_matrix(-self.yaw) @ self.t))

    def __matmul__(self, other: 'Pose4') -> 'Pose4':
        if not isinstance(other, Pose4):
            return NotImplemented
        return Pose4(self.yaw + other.yaw, self.rotation @ other.t + self.t)

    def transform_points(self, points) -> np.ndarray:
        """Points (..., 3) from frame b to frame a."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation.T + self.t

    def transform_boxes(self, boxes) -> np.ndarray:
        """Boxes (..., 7) from frame b to frame a."""
        boxes = _as_boxes(boxes)
        out = boxes.copy()
        out[..., :3] = self.transform_points(boxes[..., :3])
        out[..., 6] = wrap_angle(boxes[..., 6] + self.yaw)
        return out

    def angle_to(self, other: 'Pose4') -> float:
        """Absolute yaw difference (rad) to another pose."""
        return float(abs(wrap_angle(self.yaw - other.yaw)))

    def within(self, metres: float, degrees: float) -> bool:
        """Whether this relative pose (T_a_b) moves by at most ``metres`` and turns by at
        most ``degrees``: the two frames are at one place."""
        return bool(np.linalg.norm(self.t) <= metres and np.degrees(abs(wrap_angle(self.yaw))) <= degrees)


def kabsch_4dof(source, target, weights=None) -> Pose4:
    """Weighted least-squares 4-DoF alignment: argmin sum_i w_i |Rz(yaw) s_i + t - q_i|^2.

    ``source`` and ``target`` are corresponding points (N, 3) in gravity-aligned frames; the
    result maps source into target (``T_target_source``). Closed form: the yaw is a circular
    regression on the horizontal components of the centred points, t = mean(q) - R mean(s).
    Needs at least two points with horizontal spread and positive total weight.
    """
    s = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if s.shape != q.shape:
        raise ValueError(f'source {s.shape} and target {q.shape} must have the same shape')
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (len(s),) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError('weights must be finite, non-negative, one per point')
    if w.sum() <= 0:
        raise ValueError('kabsch_4dof needs a positive total weight')
    yaw, t = kabsch_4dof_batch(s[None], q[None], w[None])
    return Pose4(yaw[0], t[0])


def kabsch_4dof_batch(source, target, weights=None):
    """:func:`kabsch_4dof` for H problems at once: (H, N, 3) x 2 (and weights (H, N)) ->
    (yaw (H,), translation (H, 3)) of T_target_source. No input validation."""
    s = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    w = np.ones(s.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    total = w.sum(1, keepdims=True)
    s_mean = np.einsum('hn,hni->hi', w, s) / total
    q_mean = np.einsum('hn,hni->hi', w, q) / total
    sc, qc = s - s_mean[:, None], q - q_mean[:, None]
    cos_term = np.sum(w * (qc[..., 0] * sc[..., 0] + qc[..., 1] * sc[..., 1]), axis=1)
    sin_term = np.sum(w * (qc[..., 1] * sc[..., 0] - qc[..., 0] * sc[..., 1]), axis=1)
    yaw = np.arctan2(sin_term, cos_term)
    t = q_mean - np.einsum('hij,hj->hi', yaw_matrix(yaw), s_mean)
    return yaw, t


def ray_covariances(points, sigma, range_error) -> np.ndarray:
    """Covariances (N, 3, 3) of points seen from the origin: isotropic ``sigma`` (N,) plus
    ``range_error`` x distance along the viewing ray (a misjudged distance moves a point
    along its ray, the error of monocular depth)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    dist = np.maximum(np.linalg.norm(p, axis=1), 1e-9)
    ray = p / dist[:, None]
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(p),))
    range_error = np.broadcast_to(np.asarray(range_error, dtype=np.float64), (len(p),))
    return (sigma[:, None, None] ** 2 * np.eye(3)
            + (range_error * dist)[:, None, None] ** 2 * np.einsum('ni,nj->nij', ray, ray))


def align_4dof_anisotropic(source, target, cov_source, cov_target, yaw_init: float,
                           span: float = 0.35, weights=None) -> tuple[Pose4, np.ndarray]:
    """Maximum-likelihood 4-DoF alignment of points with full covariances:
    argmin sum_i w_i r_i^T (R C_s,i R^T + C_t,i)^-1 r_i with r_i = Rz(yaw) s_i + t - q_i.

    For a given yaw the translation is a weighted mean in closed form; the yaw is searched
    within ``span`` rad of ``yaw_init`` (a start from :func:`kabsch_4dof`). Returns the pose
    and each point's squared Mahalanobis residual (for robust reweighting)."""
    from scipy.optimize import minimize_scalar

    s = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=np.float64)

    def solve(yaw):
        rot = yaw_matrix(yaw)
        info = np.linalg.inv(rot @ cov_source @ rot.T + cov_target) * w[:, None, None]
        d = q - s @ rot.T
        t = np.linalg.solve(info.sum(0), np.einsum('nij,nj->i', info, d))
        r = d - t
        return t, np.einsum('ni,nij,nj->n', r, info, r)

    best = minimize_scalar(lambda y: solve(y)[1].sum(), bounds=(yaw_init - span, yaw_init + span),
                           method='bounded', options={'xatol': 1e-5})
    yaw = float(wrap_angle(best.x))
    t, chi2 = solve(yaw)
    return Pose4(yaw, t), chi2 / np.maximum(w, 1e-12)


# --------------------------------------------------------------------------------------
# Oriented 3D IoU / GIoU for yaw-only boxes: exact BEV polygon intersection x vertical overlap


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _convex_intersection_area(pa, pb) -> np.ndarray:
    """Areas (P,) of the intersections of convex CCW quadrilaterals pa, pb (P, 4, 2).

    The intersection polygon's vertices are the corners of each quad inside the other plus
    the edge-edge crossings; they are ordered by angle about their centroid and summed with
    the shoelace formula. Invalid candidate slots are replaced by the first vertex, so they
    add zero area.
    """
    n = pa.shape[0]
    tol = _LENGTH_TOL

    def inside(points, poly):
        # points (P, K, 2) inside convex CCW poly (P, 4, 2), boundary included
        edges = np.roll(poly, -1, axis=1) - poly                         # (P, 4, 2)
        rel = points[:, :, None, :] - poly[:, None, :, :]                # (P, K, 4, 2)
        lengths = np.linalg.norm(edges, axis=-1)[:, None, :]
        return np.all(_cross2(edges[:, None], rel) >= -tol * lengths, axis=2)

    in_b = inside(pa, pb)                                                # (P, 4)
    in_a = inside(pb, pa)
    da = np.roll(pa, -1, axis=1) - pa                                    # (P, 4, 2)
    db = np.roll(pb, -1, axis=1) - pb
    denom = _cross2(da[:, :, None], db[:, None, :])                      # (P, 4, 4)
    diff = pb[:, None, :, :] - pa[:, :, None, :]                         # (P, 4, 4, 2)
    parallel = np.abs(denom) < 1e-12
    safe = np.where(parallel, 1.0, denom)
    ta = _cross2(diff, db[:, None, :]) / safe
    tb = _cross2(diff, da[:, :, None]) / safe
    eps = 1e-12
    crossing = ~parallel & (ta >= -eps) & (ta <= 1 + eps) & (tb >= -eps) & (tb <= 1 + eps)
    cross_pts = pa[:, :, None, :] + ta[..., None] * da[:, :, None, :]    # (P, 4, 4, 2)

    pts = np.concatenate([pa, pb, cross_pts.reshape(n, 16, 2)], axis=1)  # (P, 24, 2)
    valid = np.concatenate([in_b, in_a, crossing.reshape(n, 16)], axis=1)
    count = valid.sum(axis=1)
    centroid = (pts * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    rel = pts - centroid[:, None, :]
    angle = np.where(valid, np.arctan2(rel[..., 1], rel[..., 0]), np.inf)
    order = np.argsort(angle, axis=1)
    pts = np.take_along_axis(pts, order[..., None], axis=1)
    valid = np.take_along_axis(valid, order, axis=1)
    pts = np.where(valid[..., None], pts, pts[:, :1, :])
    area = 0.5 * np.sum(_cross2(pts, np.roll(pts, -1, axis=1)), axis=1)
    return np.where(count >= 3, np.maximum(area, 0.0), 0.0)


def convex_hull_area(points) -> np.ndarray:
    """Areas (P,) of the convex hulls of 2D point sets (P, K, 2), K small (e.g. 8).

    Andrew's monotone chain, vectorised over P: points sorted by (x, y) build the lower
    chain, the reversed order the upper chain, each with a stack that pops while the last
    turn is not strictly counter-clockwise. Rounding can only keep or drop nearly collinear
    points, which changes the area by a rounding-sized amount; the walk always ends.
    """
    p = np.asarray(points, dtype=np.float64)
    n, k = p.shape[:2]
    rows = np.arange(n)
    order = np.lexsort((p[..., 1], p[..., 0]), axis=-1)
    p = np.take_along_axis(p, order[..., None], axis=1)

    def chain_area(pts):
        stack = np.zeros_like(pts)
        size = np.zeros(n, dtype=np.int64)
        for j in range(k):
            q = pts[:, j]
            for _ in range(k):
                a = stack[rows, np.maximum(size - 2, 0)]
                b = stack[rows, np.maximum(size - 1, 0)]
                pop = (size >= 2) & (_cross2(b - a, q - a) <= 0)
                if not np.any(pop):
                    break
                size -= pop
            stack[rows, size] = q
            size += 1
        links = _cross2(stack[:, :-1], stack[:, 1:])           # h_i x h_(i+1)
        return np.sum(np.where(np.arange(k - 1) < (size - 1)[:, None], links, 0.0), axis=1)

    return np.maximum(0.5 * (chain_area(p) + chain_area(p[:, ::-1])), 0.0)


def _iou_terms(a, b):
    """Intersection and union volumes (P,) and the vertical span (P,) of paired boxes."""
    area_a, area_b = a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]
    a_bottom, a_top = a[:, 2] - a[:, 5] / 2, a[:, 2] + a[:, 5] / 2
    b_bottom, b_top = b[:, 2] - b[:, 5] / 2, b[:, 2] + b[:, 5] / 2
    overlap = np.maximum(0.0, np.minimum(a_top, b_top) - np.maximum(a_bottom, b_bottom))
    # Only pairs whose footprints' circumscribed circles meet can intersect.
    reach = 0.5 * (np.hypot(a[:, 3], a[:, 4]) + np.hypot(b[:, 3], b[:, 4]))
    near = ((np.hypot(a[:, 0] - b[:, 0], a[:, 1] - b[:, 1]) <= reach) & (overlap > 0)
            & (area_a > 0) & (area_b > 0))
    inter_area = np.zeros(len(a))
    if np.any(near):
        clipped = _convex_intersection_area(bev_corners(a[near]), bev_corners(b[near]))
        inter_area[near] = np.minimum(clipped, np.minimum(area_a[near], area_b[near]))
    inter = inter_area * overlap
    union = box_volume(a) + box_volume(b) - inter
    height = np.maximum(a_top, b_top) - np.minimum(a_bottom, b_bottom)
    return inter, union, height


def _pairs(a, b):
    a = _as_boxes(a).reshape(-1, BOX_DIM)
    b = _as_boxes(b).reshape(-1, BOX_DIM)
    ia, ib = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing='ij')
    return a[ia.ravel()], b[ib.ravel()], (len(a), len(b))


_CHUNK = 4096  # pairs per vectorised batch: bounds temporary memory to a few tens of MB


def _chunked(fn):
    """Apply a paired-box function in chunks of ``_CHUNK`` pairs."""
    def wrapper(a, b):
        a = _as_boxes(a).reshape(-1, BOX_DIM)
        b = _as_boxes(b).reshape(-1, BOX_DIM)
        if a.shape != b.shape:
            raise ValueError(f'paired boxes need equal shapes, got {a.shape} and {b.shape}')
        if len(a) == 0:
            return np.zeros(0)
        return np.concatenate([fn(a[i:i + _CHUNK], b[i:i + _CHUNK])
                               for i in range(0, len(a), _CHUNK)])
    wrapper.__name__, wrapper.__doc__ = fn.__name__, fn.__doc__
    return wrapper


def _ratio(num, den):
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


@_chunked
def iou_3d_paired(a, b) -> np.ndarray:
    """Exact 3D IoU of yaw-oriented boxes a[i] and b[i]: (P, 7), (P, 7) -> (P,)."""
    inter, union, _ = _iou_terms(a, b)
    return np.clip(_ratio(inter, union), 0.0, 1.0)


def iou_3d(a, b) -> np.ndarray:
    """Exact 3D IoU between every box of a (N, 7) and every box of b (M, 7) -> (N, M)."""
    pa, pb, shape = _pairs(a, b)
    return iou_3d_paired(pa, pb).reshape(shape)


@_chunked
def giou_3d_paired(a, b) -> np.ndarray:
    """Generalized 3D IoU in [-1, 1] of boxes a[i], b[i]: (P, 7), (P, 7) -> (P,).

    The enclosing volume is the convex hull of both footprints times the vertical span of
    both boxes: GIoU = IoU - (C - U) / C.
    """
    inter, union, height = _iou_terms(a, b)
    hull = convex_hull_area(np.concatenate([bev_corners(a), bev_corners(b)], axis=1))
    enclosing = np.maximum(hull * height, union)
    iou = np.clip(_ratio(inter, union), 0.0, 1.0)
    return np.clip(iou - _ratio(enclosing - union, enclosing), -1.0, 1.0)


def giou_3d(a, b) -> np.ndarray:
    """Generalized 3D IoU between every box of a (N, 7) and of b (M, 7) -> (N, M)."""
    pa, pb, shape = _pairs(a, b)
    return giou_3d_paired(pa, pb).reshape(shape)
