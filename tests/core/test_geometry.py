"""rfm_core.geometry: boxes, transforms, gravity, Kabsch-4DoF, exact oriented 3D IoU/GIoU."""
import numpy as np
import pytest

from rfm_core.geometry import (
    CORNER_SIGNS, Pose4, align_4dof_anisotropic, bev_corners, box_corners, box_volume, boxes_from_oriented,
    giou_3d, giou_3d_paired, gravity_aligned_rotation, gravity_from_accelerometer, iou_3d,
    iou_3d_paired, kabsch_4dof, matrix_from_quaternion, oriented_from_boxes,
    quaternion_from_matrix, ray_covariances, wrap_angle, yaw_matrix,
)

UNIT = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0])


def random_boxes(rng, n, spread=1.5):
    return np.c_[rng.uniform(-spread, spread, (n, 3)), rng.uniform(0.1, 2.0, (n, 3)),
                 rng.uniform(-np.pi, np.pi, n)]


def random_rotation(rng):
    q = rng.normal(size=4)
    return matrix_from_quaternion(q)


# ---------------------------------------------------------------- boxes and corners

def test_corner_order_is_documented_one():
    corners = box_corners(np.array([1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 0.0]))
    np.testing.assert_allclose(corners, [1, 2, 3] + CORNER_SIGNS * [1, 2, 3])
    # bottom face first, counter-clockwise seen from above; corner i+4 above corner i
    assert np.all(corners[:4, 2] == 0.0) and np.all(corners[4:, 2] == 6.0)
    np.testing.assert_allclose(corners[4:, :2], corners[:4, :2])
    footprint = bev_corners(np.array([0, 0, 0, 2.0, 1.0, 1.0, 0.3]))
    x, y = footprint[:, 0], footprint[:, 1]     # counter-clockwise: positive shoelace area
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) == pytest.approx(2.0)


def test_corners_rotate_with_yaw():
    box = np.array([0.0, 0.0, 0.0, 2.0, 1.0, 1.0, np.pi / 2])
    np.testing.assert_allclose(box_corners(box)[0], [0.5, -1.0, -0.5], atol=1e-12)
    assert box_volume(box) == pytest.approx(2.0)


def test_boxes_from_oriented_handles_axis_permutations():
    box = np.array([0.3, -1.0, 0.7, 1.2, 0.4, 0.9, 0.6])
    centers, rotations, sizes = oriented_from_boxes(box)
    # The same box described by a detector whose local y axis is the vertical one:
    # the columns of perm are its local axes written in the box's (x, y, z) axes.
    perm = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]])
    rot2 = rotations[0] @ perm
    size2 = perm.T @ sizes[0]
    out = boxes_from_oriented(centers, rot2[None], size2[None])[0]
    assert iou_3d(out, box)[0, 0] == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(box_corners(out)[np.lexsort(box_corners(out).T)],
                               box_corners(box)[np.lexsort(box_corners(box).T)], atol=1e-9)


def test_wrap_angle():
    np.testing.assert_allclose(wrap_angle([np.pi, -np.pi, 3 * np.pi / 2, 0.1]),
                               [-np.pi, -np.pi, -np.pi / 2, 0.1])


# ---------------------------------------------------------------- 4-DoF poses

def test_pose4_compose_inverse_matrix_quaternion():
    a = Pose4(0.7, (1.0, -2.0, 0.5))
    b = Pose4(-2.9, (0.3, 0.1, -1.0))
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    np.testing.assert_allclose((a @ a.inverse()).matrix(), np.eye(4), atol=1e-12)
    assert Pose4.from_matrix(a.matrix()) == a
    q = a.quaternion()
    np.testing.assert_allclose(matrix_from_quaternion(q), a.rotation, atol=1e-12)
    again = Pose4.from_quaternion(q, a.t)
    assert again.yaw == pytest.approx(a.yaw) and np.allclose(again.t, a.t)
    p = np.array([[1.0, 2.0, 3.0], [-1.0, 0.0, 2.0]])
    np.testing.assert_allclose(a.transform_points(p), (a.matrix() @ np.c_[p, np.ones(2)].T).T[:, :3])


def test_pose4_yaw_wraps_across_pi():
    a = Pose4(3.0, (0, 0, 0)) @ Pose4(0.5, (0, 0, 0))
    assert a.yaw == pytest.approx(3.5 - 2 * np.pi)
    assert Pose4(np.pi - 0.01).angle_to(Pose4(-np.pi + 0.01)) == pytest.approx(0.02)


def test_pose4_rejects_roll_pitch():
    m = np.eye(4)
    m[:3, :3] = matrix_from_quaternion([np.sin(0.1), 0.0, 0.0, np.cos(0.1)])
    with pytest.raises(ValueError, match='yaw'):
        Pose4.from_matrix(m)


def test_pose4_transform_boxes_preserves_shape():
    rng = np.random.default_rng(1)
    boxes = random_boxes(rng, 5)
    pose = Pose4(1.2, (0.5, 0.2, -0.3))
    moved = pose.transform_boxes(boxes)
    np.testing.assert_allclose(box_corners(moved), pose.transform_points(box_corners(boxes)), atol=1e-12)


def test_quaternion_round_trip_general_rotations():
    rng = np.random.default_rng(2)
    rotations = np.stack([random_rotation(rng) for _ in range(200)])
    # include the Shepperd branches with w ~ 0
    rotations = np.concatenate([rotations, [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]),
                                            np.diag([-1.0, -1, 1])]])
    q = quaternion_from_matrix(rotations)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0)
    np.testing.assert_allclose(matrix_from_quaternion(q), rotations, atol=1e-12)


# ---------------------------------------------------------------- gravity

def test_gravity_aligned_rotation_level_camera():
    # Level camera: gravity along +y (down in the image).
    r = gravity_aligned_rotation([0.0, 9.81, 0.0])
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-12)   # forward -> x
    np.testing.assert_allclose(r @ [0, -1, 0], [0, 0, 1], atol=1e-12)  # image up -> z
    np.testing.assert_allclose(r @ [-1, 0, 0], [0, 1, 0], atol=1e-12)  # left -> y
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_gravity_aligned_rotation_tilted_and_straight_down():
    rng = np.random.default_rng(3)
    for _ in range(50):
        g = rng.normal(size=3)
        r = gravity_aligned_rotation(g)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(r @ (g / np.linalg.norm(g)), [0, 0, -1], atol=1e-12)
        fwd = r @ [0, 0, 1]
        assert abs(fwd[1]) < 1e-9 and fwd[0] >= -1e-12     # heading is the x axis
    r = gravity_aligned_rotation([0.0, 0.0, 1.0])              # looking straight down
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(r @ [0, -1, 0], [1, 0, 0], atol=1e-12)
    with pytest.raises(ValueError):
        gravity_aligned_rotation([0.0, 0.0, 0.0])


def test_gravity_from_accelerometer_points_down():
    np.testing.assert_allclose(gravity_from_accelerometer([0.0, -9.81, 0.0]), [0, 1, 0])
    with pytest.raises(ValueError):
        gravity_from_accelerometer([np.nan, 0, 0])


# ---------------------------------------------------------------- Kabsch 4-DoF

def test_kabsch_4dof_exact_at_zero_noise():
    rng = np.random.default_rng(4)
    truth = Pose4(2.4, (1.5, -0.7, 0.2))
    src = rng.uniform(-3, 3, (16, 3))
    est = kabsch_4dof(src, truth.transform_points(src))
    assert np.linalg.norm(est.t - truth.t) < 1e-3          # < 1 mm
    assert np.degrees(est.angle_to(truth)) < 0.05            # < 0.05 deg
    assert np.linalg.norm(est.t - truth.t) < 1e-9            # in fact exact


def test_kabsch_4dof_degrades_gracefully_with_noise():
    rng = np.random.default_rng(5)
    truth = Pose4(-1.1, (0.4, 2.0, -0.1))
    src = rng.uniform(-2, 2, (64, 3))
    errors = []
    for sigma in (0.005, 0.02, 0.05):
        est = kabsch_4dof(src, truth.transform_points(src) + rng.normal(0, sigma, src.shape))
        errors.append((np.linalg.norm(est.t - truth.t), np.degrees(est.angle_to(truth))))
    # error grows with noise but stays of the order of sigma / sqrt(N)
    assert errors[0][0] < 0.005 and errors[2][0] < 0.05
    assert errors[0][1] < 0.3 and errors[2][1] < 2.0
    assert errors[0][0] < errors[2][0]


def test_kabsch_4dof_with_outliers_given_weights():
    rng = np.random.default_rng(6)
    truth = Pose4(0.9, (-1.0, 0.5, 0.3))
    src = rng.uniform(-2, 2, (40, 3))
    dst = truth.transform_points(src) + rng.normal(0, 0.01, src.shape)
    outliers = rng.choice(40, 12, replace=False)             # 30 %
    dst[outliers] += rng.uniform(-3, 3, (12, 3))
    unweighted = kabsch_4dof(src, dst)
    weights = np.ones(40)
    weights[outliers] = 0.0
    weighted = kabsch_4dof(src, dst, weights)
    assert np.linalg.norm(weighted.t - truth.t) < 0.02
    assert np.degrees(weighted.angle_to(truth)) < 1.0
    assert np.linalg.norm(unweighted.t - truth.t) > 3 * np.linalg.norm(weighted.t - truth.t)


def test_kabsch_4dof_input_errors():
    with pytest.raises(ValueError):
        kabsch_4dof(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError):
        kabsch_4dof(np.zeros((3, 3)), np.zeros((3, 3)), weights=[0, 0, 0])


def test_ray_covariances_stretch_along_the_viewing_ray():
    points = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 4.0]])
    cov = ray_covariances(points, [0.01, 0.02], 0.05)
    for p, c, sigma in zip(points, cov, (0.01, 0.02)):
        values, vectors = np.linalg.eigh(c)
        d = np.linalg.norm(p)
        np.testing.assert_allclose(values, [sigma ** 2, sigma ** 2, sigma ** 2 + (0.05 * d) ** 2])
        assert abs(vectors[:, 2] @ p / d) == pytest.approx(1.0)       # the long axis is the ray


def test_anisotropic_alignment_beats_kabsch_under_along_ray_noise():
    """Points whose distance from each camera is misjudged (5%) but whose bearing is nearly
    right (1 cm): the maximum-likelihood fit uses the bearings; plain Kabsch cannot."""
    rng = np.random.default_rng(7)
    t_iso, t_ml = [], []
    for _ in range(40):
        truth = Pose4(rng.uniform(-0.5, 0.5), rng.uniform(-1, 1, 3) * [1, 1, 0.1])
        a = rng.uniform([-2, -1, 1], [2, 1, 5], (6, 3))                  # in front of camera a
        b = truth.transform_points(a)
        noisy = []
        for p in (a, b):
            p = p * (1 + rng.normal(0, 0.05, (len(p), 1))) + rng.normal(0, 0.01, p.shape)
            noisy.append(p)
        start = kabsch_4dof(*noisy)
        cov = [ray_covariances(p, 0.01, 0.05) for p in noisy]
        fit, chi2 = align_4dof_anisotropic(noisy[0], noisy[1], cov[0], cov[1], start.yaw)
        assert chi2.shape == (6,) and np.all(chi2 >= 0)
        t_iso.append(np.linalg.norm(start.t - truth.t))
        t_ml.append(np.linalg.norm(fit.t - truth.t))
    assert np.median(t_ml) < 0.6 * np.median(t_iso)
    exact = align_4dof_anisotropic(a, b, *[ray_covariances(p, 0.01, 0.05) for p in (a, b)], 0.0)[0]
    assert np.linalg.norm(exact.t - truth.t) < 1e-4 and np.degrees(exact.angle_to(truth)) < 0.01


# ---------------------------------------------------------------- IoU / GIoU hand cases

def test_iou_identical_is_one():
    assert iou_3d(UNIT, UNIT)[0, 0] == pytest.approx(1.0, abs=1e-12)
    rotated = UNIT.copy()
    rotated[6] = 0.83
    assert iou_3d(rotated, rotated)[0, 0] == pytest.approx(1.0, abs=1e-12)
    assert giou_3d(rotated, rotated)[0, 0] == pytest.approx(1.0, abs=1e-12)


def test_iou_half_overlap_axis_aligned_is_one_third():
    shifted = UNIT + [0.5, 0, 0, 0, 0, 0, 0]
    assert iou_3d(UNIT, shifted)[0, 0] == pytest.approx(1 / 3, abs=1e-12)
    up = UNIT + [0, 0, 0.5, 0, 0, 0, 0]
    assert iou_3d(UNIT, up)[0, 0] == pytest.approx(1 / 3, abs=1e-12)


def test_iou_45_degree_rotated_square():
    rotated = UNIT + [0, 0, 0, 0, 0, 0, np.pi / 4]
    octagon = 2 * (np.sqrt(2) - 1)          # area of the unit square cut by its 45-degree copy
    assert iou_3d(UNIT, rotated)[0, 0] == pytest.approx(octagon / (2 - octagon), abs=1e-12)
    # Enclosing hull: regular octagon of circumradius sqrt(2)/2 -> area sqrt(2).
    union = 2 - octagon
    expected_giou = octagon / union - (np.sqrt(2) - union) / np.sqrt(2)
    assert giou_3d(UNIT, rotated)[0, 0] == pytest.approx(expected_giou, abs=1e-12)


def test_iou_disjoint_and_touching():
    far = UNIT + [3, 0, 0, 0, 0, 0, 0]
    assert iou_3d(UNIT, far)[0, 0] == 0.0
    # enclosing 4 x 1 x 1, union 2 -> GIoU = 0 - (4 - 2) / 4
    assert giou_3d(UNIT, far)[0, 0] == pytest.approx(-0.5)
    touching = UNIT + [1, 0, 0, 0, 0, 0, 0]
    assert iou_3d(UNIT, touching)[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert giou_3d(UNIT, touching)[0, 0] == pytest.approx(0.0, abs=1e-12)
    above = UNIT + [0, 0, 2, 0, 0, 0, 0]
    assert iou_3d(UNIT, above)[0, 0] == 0.0


def test_iou_nested_and_degenerate():
    small = np.array([0.1, 0.0, 0.0, 0.5, 0.5, 0.5, 0.4])
    assert iou_3d(UNIT, small)[0, 0] == pytest.approx(0.125)
    flat = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0])
    assert iou_3d(UNIT, flat)[0, 0] == 0.0
    assert iou_3d(flat, flat)[0, 0] == 0.0


def test_iou_shapes_and_paired():
    rng = np.random.default_rng(7)
    a, b = random_boxes(rng, 6), random_boxes(rng, 4)
    full = iou_3d(a, b)
    assert full.shape == (6, 4)
    np.testing.assert_allclose(iou_3d_paired(a[:4], b), np.diag(full[:4]), atol=1e-12)
    np.testing.assert_allclose(giou_3d_paired(a[:4], b), np.diag(giou_3d(a, b)[:4]), atol=1e-12)
    assert iou_3d(np.zeros((0, 7)), b).shape == (0, 4)
    with pytest.raises(ValueError):
        iou_3d(np.zeros((2, 6)), b)


def monte_carlo_iou(a, b, rng, n=200_000):
    """IoU from uniform samples in a box enclosing both."""
    corners = np.concatenate([box_corners(a), box_corners(b)])
    lo, hi = corners.min(0), corners.max(0)
    pts = rng.uniform(lo, hi, (n, 3))

    def inside(box):
        local = (pts - box[:3]) @ yaw_matrix(box[6])      # rotate into the box frame
        return np.all(np.abs(local) <= box[3:6] / 2, axis=1)

    ina, inb = inside(a), inside(b)
    union = np.count_nonzero(ina | inb)
    return np.count_nonzero(ina & inb) / union if union else 0.0


def test_iou_matches_monte_carlo_volume_estimate():
    rng = np.random.default_rng(8)
    a = random_boxes(rng, 40, spread=0.6)
    b = random_boxes(rng, 40, spread=0.6)
    exact = iou_3d_paired(a, b)
    estimate = np.array([monte_carlo_iou(x, y, rng) for x, y in zip(a, b)])
    assert np.count_nonzero(exact > 0.05) >= 15              # the sample has real overlaps
    np.testing.assert_allclose(exact, estimate, atol=1e-2)


def reference_giou(a, b):
    """GIoU with the enclosing footprint from scipy's ConvexHull (Qhull)."""
    from scipy.spatial import ConvexHull
    iou = iou_3d_paired(a, b)[0]
    inter_union = box_volume(a) + box_volume(b)
    union = inter_union / (1 + iou)          # from IoU = I / U and I + U = Va + Vb
    pts = np.concatenate([bev_corners(a), bev_corners(b)])
    hull = ConvexHull(pts).volume             # area in 2D
    height = max(a[2] + a[5] / 2, b[2] + b[5] / 2) - min(a[2] - a[5] / 2, b[2] - b[5] / 2)
    enclosing = hull * height
    return iou - (enclosing - union) / enclosing


def test_giou_matches_qhull_including_near_degenerate_pairs():
    rng = np.random.default_rng(9)
    pairs = [(random_boxes(rng, 1)[0], random_boxes(rng, 1)[0]) for _ in range(60)]
    for yaw in (0.0, 1e-12, 1e-7, np.pi / 2 - 1e-12):
        for offset in ([0, 1, 0], [1, 0, 0], [1, 1, 0], [0.3, 1, 0.2], [0, 0, 0], [0, -2, 0],
                       [2, 0.5, 0], [-1, 0, 0.5]):
            a = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0])
            b = a.copy()
            b[:3] += offset
            b[6] = yaw
            pairs.append((a, b))
    got = np.array([giou_3d_paired(a, b)[0] for a, b in pairs])
    want = np.array([reference_giou(a, b) for a, b in pairs])
    np.testing.assert_allclose(got, want, atol=1e-9)
