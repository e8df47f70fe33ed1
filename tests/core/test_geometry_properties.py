"""Property tests (hypothesis) for IoU/GIoU and 4-DoF poses."""
import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from rfm_core.geometry import Pose4, giou_3d_paired, iou_3d_paired, kabsch_4dof

coord = st.floats(-2.0, 2.0, allow_nan=False)
extent = st.floats(0.05, 2.0, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
box = st.tuples(coord, coord, coord, extent, extent, extent, angle).map(np.array)
pose = st.tuples(angle, st.tuples(coord, coord, coord)).map(lambda a: Pose4(a[0], a[1]))
SETTINGS = settings(max_examples=150, deadline=None)


@SETTINGS
@given(box, box)
def test_iou_is_symmetric_and_bounded(a, b):
    ab, ba = iou_3d_paired(a, b)[0], iou_3d_paired(b, a)[0]
    assert 0.0 <= ab <= 1.0
    assert abs(ab - ba) < 1e-9


UNIT = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0])


@SETTINGS
@given(box, box)
# touching boxes with nearly collinear footprint edges (once broke the hull walk)
@example(UNIT, np.array([0.0, -1.0, 0.0, 1.0, 1.0, 1.0, 1e-12]))
@example(UNIT, np.array([0.0, -1.0, 0.0, 1.0, 1.0, 2.0, 1e-12]))
@example(UNIT, np.array([0.0, -2.0, 0.0, 1.0, 1.0, 1.0, 1e-12]))
def test_giou_is_bounded_and_below_iou(a, b):
    g = giou_3d_paired(a, b)[0]
    assert -1.0 <= g <= 1.0
    assert g <= iou_3d_paired(a, b)[0] + 1e-9
    assert abs(g - giou_3d_paired(b, a)[0]) < 1e-9


@SETTINGS
@given(box, box, pose)
def test_iou_and_giou_invariant_under_shared_4dof_transform(a, b, t):
    ta, tb = t.transform_boxes(a), t.transform_boxes(b)
    assert abs(iou_3d_paired(a, b)[0] - iou_3d_paired(ta, tb)[0]) < 1e-7
    assert abs(giou_3d_paired(a, b)[0] - giou_3d_paired(ta, tb)[0]) < 1e-7


@SETTINGS
@given(box)
def test_self_iou_is_one(a):
    assert abs(iou_3d_paired(a, a)[0] - 1.0) < 1e-9
    assert abs(giou_3d_paired(a, a)[0] - 1.0) < 1e-9


@SETTINGS
@given(pose, pose)
def test_pose_composition_matches_matrices(a, b):
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), atol=1e-9)
    np.testing.assert_allclose((a.inverse() @ a).matrix(), np.eye(4), atol=1e-9)


@SETTINGS
@given(pose, st.integers(0, 2**32 - 1))
def test_kabsch_recovers_any_pose(t, seed):
    pts = np.random.default_rng(seed).uniform(-3, 3, (8, 3))
    est = kabsch_4dof(pts, t.transform_points(pts))
    assert est.angle_to(t) < 1e-9
    assert np.linalg.norm(est.t - t.t) < 1e-9
