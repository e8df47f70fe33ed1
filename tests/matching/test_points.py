"""Relative poses refined on depth points (rfm_core.matching.points, relative_pose.with_points)."""
from dataclasses import replace

import numpy as np
import pytest

from rfm_core.detection import make_detector
from rfm_core.geometry import Pose4
from rfm_core.matching.classical import ObjectMatches
from rfm_core.matching.config import MatchingConfig
from rfm_core.clouds import PointIndex, depth_cloud, seen_through_both
from rfm_core.matching.points import align_points
from rfm_core.matching.relative_pose import RelativePose, estimate_relative_pose, with_surfaces, with_points
from rfm_core.observations import CameraIntrinsics, FrameObservations
from rfm_core.sim.capture import Capture, CaptureConfig

INTR = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)


def _room(rng, walls=(True, True), boxes=True, spacing=0.05):
    """Points of a room corner in a gravity-aligned camera frame: the floor 1.5 m below,
    walls across x = 3 and y = 2 (as asked) and two boxes on the floor."""
    g = np.arange(-1.0, 3.0, spacing)
    parts = [np.c_[np.stack(np.meshgrid(g, g - 1.0), -1).reshape(-1, 2), np.full(len(g) ** 2, -1.5)]]
    h = np.arange(-1.5, 1.0, spacing)
    if walls[0]:
        parts.append(np.c_[np.full(len(g) * len(h), 3.0), np.stack(np.meshgrid(g - 1.0, h), -1).reshape(-1, 2)])
    if walls[1]:
        parts.append(np.c_[np.stack(np.meshgrid(g, h), -1).reshape(-1, 2)[:, :1], np.full(len(g) * len(h), 2.0),
                           np.stack(np.meshgrid(g, h), -1).reshape(-1, 2)[:, 1:]])
    if boxes:
        for cx, cy, size in ((1.5, 0.5, 0.6), (2.2, -0.6, 0.4)):
            s = np.arange(-size / 2, size / 2, spacing / 2)
            u, v = (a.ravel() for a in np.meshgrid(s, s))
            for sign in (-1, 1):               # two faces and the top
                parts.append(np.c_[cx + sign * size / 2 + 0 * u, cy + u, -1.5 + size / 2 + v])
            parts.append(np.c_[cx + u, cy + v, np.full(len(u), -1.5 + size)])
    pts = np.concatenate(parts)
    return pts + rng.normal(0, 0.003, pts.shape)


def _seen_from(points, pose: Pose4, rng):
    """The points in a frame whose pose in theirs is ``pose`` (T_theirs_frame), re-sampled."""
    moved = pose.inverse().transform_points(points)
    return moved[rng.permutation(len(moved))[: len(moved) * 3 // 4]]


def test_depth_cloud_is_the_image_in_the_gravity_aligned_frame_one_point_per_cell():
    depth = np.full((240, 320), 2.0, np.float32)                 # a wall 2 m ahead of a level camera
    depth[:10] = np.nan
    depth[-10:] = 9.0                                           # beyond the range: dropped
    cloud = depth_cloud(depth, INTR, [0.0, 1.0, 0.0], voxel_m=0.1, max_range_m=6.0)
    assert cloud.dtype == np.float32 and cloud.shape[1] == 3
    np.testing.assert_allclose(cloud[:, 0], 2.0, atol=1e-5)     # x: forward
    # the wall spans 3.2 x ~2.2 m in view: about one point per 10 cm cell
    assert 500 < len(cloud) < 800
    assert np.all(cloud[:, 2] <= 1.2 + 1e-6) and np.all(cloud[:, 2] >= -1.0 - 0.06)   # z up, no far rows
    assert depth_cloud(depth, INTR, [0.0, 1.0, 0.0], voxel_m=0.0, max_range_m=6.0).shape == (0, 3)


def test_points_align_two_views_from_a_pose_centimetres_and_degrees_off():
    rng = np.random.default_rng(0)
    room = _room(rng)
    truth = Pose4(np.radians(15.0), (0.4, -0.3, 0.05))            # T_fixed_moving
    moving = _seen_from(room, truth, rng)
    start = Pose4(truth.yaw + np.radians(6.0), np.asarray(truth.t) + [0.15, -0.12, 0.04])
    found = align_points(start, moving, PointIndex(room))
    assert found is not None and found.free == 0
    assert np.degrees(found.pose.angle_to(truth)) < 0.05
    assert np.linalg.norm(np.asarray(found.pose.t) - truth.t) < 0.005
    assert found.overlap > 0.9 and found.overlap > found.overlap_before and found.residual_m < 0.005


def test_what_the_points_do_not_fix_stays_where_the_start_put_it():
    """The floor and one wall across x fix the height, x and the yaw; nothing fixes y, which
    keeps the starting pose's value instead of drifting."""
    rng = np.random.default_rng(1)
    room = _room(rng, walls=(True, False), boxes=False)
    truth = Pose4(np.radians(5.0), (0.3, 0.2, 0.0))
    moving = _seen_from(room, truth, rng)
    start = Pose4(truth.yaw + np.radians(2.0), np.asarray(truth.t) + [0.08, 0.1, 0.03])
    found = align_points(start, moving, PointIndex(room))
    assert found is not None and found.free == 1
    t = np.asarray(found.pose.t)
    assert abs(t[0] - truth.t[0]) < 0.01 and abs(t[2] - truth.t[2]) < 0.005
    assert np.degrees(found.pose.angle_to(truth)) < 0.1
    assert t[1] == pytest.approx(start.t[1], abs=0.02)            # the boxes' y, not a slide along the wall


def test_a_tilt_between_the_two_frames_gravity_is_aligned_and_the_camera_placed():
    """Each frame's gravity is the IMU filter's estimate: 2 deg apart, a room 3 m away is
    misplaced by 10 cm. 4-DoF leaves the points off their surfaces; with ``tilt`` they go back on
    and the camera's position and yaw come out right (the tilt itself is reported)."""
    rng = np.random.default_rng(4)
    room = _room(rng)
    truth = Pose4(np.radians(12.0), (0.35, -0.2, 0.03))            # T_fixed_moving
    moving = _seen_from(room, truth, rng)
    c, s = np.cos(np.radians(2.0)), np.sin(np.radians(2.0))
    moving = moving @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]).T   # its gravity 2 deg off, about y
    start = Pose4(truth.yaw + np.radians(3.0), np.asarray(truth.t) + [0.06, -0.05, 0.02])
    flat = align_points(start, moving, PointIndex(room))
    tilted = align_points(start, moving, PointIndex(room), tilt=True)
    assert tilted is not None and tilted.free == 0 and tilted.tilt_deg == pytest.approx(2.0, abs=0.1)
    assert tilted.overlap > 0.9 and tilted.overlap > flat.overlap + 0.1
    assert np.linalg.norm(np.asarray(flat.pose.t) - truth.t) > 0.03                # the tilt pulls 4-DoF off
    assert np.linalg.norm(np.asarray(tilted.pose.t) - truth.t) < 0.01
    assert np.degrees(tilted.pose.angle_to(truth)) < 0.1
    # level frames: the same pose either way
    level = align_points(start, _seen_from(room, truth, rng), PointIndex(room), tilt=True)
    assert level.tilt_deg < 0.1 and np.linalg.norm(np.asarray(level.pose.t) - truth.t) < 0.005


def test_a_stream_aligns_from_its_prediction_where_the_boxes_put_the_frame_far_off():
    """Two boxes cut by the image border can place a frame decimetres off, beyond where the
    alignment from their pose finds the surfaces; the prediction from the frame before is
    near, and the alignment that puts more points on the surfaces is kept."""
    rng = np.random.default_rng(5)
    room = _room(rng)
    truth = Pose4(np.radians(-8.0), (0.3, 0.25, 0.0))
    source = FrameObservations(0, 'c', INTR, [0, 0, -1], cloud=room)
    target = FrameObservations(1, 'c', INTR, [0, 0, -1], cloud=_seen_from(room, truth, rng))
    boxes = RelativePose(Pose4(truth.yaw + np.radians(4.0), np.asarray(truth.t) + [0.45, -0.4, 0.0]),
                         np.zeros((0, 2), int), np.zeros(0), np.zeros(0), 0.0, 2)
    predicted = Pose4(truth.yaw + np.radians(0.5), np.asarray(truth.t) + [0.02, 0.02, 0.0])
    alone = with_points(replace(boxes), source, target)
    assert np.linalg.norm(np.asarray(alone.pose.t) - truth.t) > 0.1          # the boxes' pose is too far off
    found = with_points(replace(boxes), source, target, predicted=predicted)
    assert np.linalg.norm(np.asarray(found.pose.t) - truth.t) < 0.005


def test_a_relative_pose_is_refined_where_the_points_overlap_and_kept_where_they_do_not():
    rng = np.random.default_rng(2)
    room = _room(rng)
    truth = Pose4(np.radians(-10.0), (0.25, 0.35, -0.02))          # T_source_target
    source = FrameObservations(0, 'c', INTR, [0, 0, -1], cloud=room)
    target = FrameObservations(1, 'c', INTR, [0, 0, -1], cloud=_seen_from(room, truth, rng))
    boxes = RelativePose(Pose4(truth.yaw + np.radians(2.5), np.asarray(truth.t) + [0.09, -0.07, 0.02]),
                         np.zeros((0, 2), int), np.zeros(0), np.zeros(0), 0.0, 2)
    fixed = with_points(replace(boxes), source, target)
    assert np.linalg.norm(np.asarray(fixed.pose.t) - truth.t) < 0.005
    assert np.degrees(fixed.pose.angle_to(truth)) < 0.05
    # another place altogether (the points 3 m away): nothing overlaps, the boxes' pose stays
    elsewhere = FrameObservations(1, 'c', INTR, [0, 0, -1], cloud=target.cloud + [3.0, 3.0, 0.0])
    assert with_points(replace(boxes), source, elsewhere).pose == boxes.pose
    # a frame without points: the boxes' pose
    assert with_points(replace(boxes), source, FrameObservations(1, 'c', INTR, [0, 0, -1])).pose == boxes.pose
    # a correction beyond the bounds is refused
    tight = MatchingConfig(point_max_correction_m=0.05)
    assert with_points(replace(boxes), source, target, tight).pose == boxes.pose
    with pytest.raises(ValueError, match='cloud'):
        FrameObservations(1, 'c', INTR, [0, 0, -1], cloud=[[0.0, np.nan, 1.0]])


def test_depth_points_correct_the_boxes_relative_pose_between_rendered_views():
    """Two views of a simulated handheld walk 1.2 s apart through the depth detector: the
    boxes, floor and walls put the second camera centimetres off; the points put it within
    about a centimetre (median of the pairs), and never further off than the boxes did by
    more than a centimetre."""
    cap = Capture(CaptureConfig(seed=44, frames=40, fps=10.0, room_style='textured'))
    frames = list(cap.frames())
    det = make_detector('depth_clusters')
    obs = [det.detect(f.detector_input()) for f in frames]
    assert all(len(o.cloud) > 300 for o in obs)
    cfg = MatchingConfig()
    errors = []
    for i in range(0, 28, 3):
        a, b = obs[i], obs[i + 12]
        m = ObjectMatches(*_true_matches(a, b, frames[i], frames[i + 12]))
        rel = estimate_relative_pose(b.boxes, a.boxes, m, cfg)
        if rel is None:
            continue
        rel.swap_index_order()
        truth = frames[i].aligned_from_map() @ frames[i + 12].aligned_from_map().inverse()   # T_a_b
        with_surfaces(rel, a, b, cfg, points=False)
        before = np.linalg.norm(np.asarray(rel.pose.t) - truth.t)
        with_points(rel, a, b)
        after = np.linalg.norm(np.asarray(rel.pose.t) - truth.t)
        errors.append((before, after, np.degrees(rel.pose.angle_to(truth))))
    errors = np.array(errors)
    assert len(errors) >= 5, errors
    assert np.median(errors[:, 1]) < 0.012 and np.median(errors[:, 1]) < np.median(errors[:, 0]), errors
    assert np.all(errors[:, 1] < errors[:, 0] + 0.01) and np.median(errors[:, 2]) < 0.3, errors


def _true_matches(a, b, fa, fb):
    """Matches of b's detections to a's by the simulator's boxes: the nearest true object."""
    ids_a, ids_b = _object_ids(a, fa), _object_ids(b, fb)
    pairs = [(j, i) for j, ob in enumerate(ids_b) for i, oa in enumerate(ids_a) if ob >= 0 and ob == oa]
    rows = np.array([p[0] for p in pairs], int)
    cols = np.array([p[1] for p in pairs], int)
    return rows, cols, np.ones(len(pairs))


def _object_ids(obs, frame):
    truth = frame.ground_truth
    out = []
    for box in obs.boxes:
        d = np.linalg.norm(truth.boxes[:, :3] - box[:3], axis=1) if len(truth.boxes) else np.array([9.0])
        out.append(int(truth.object_ids[np.argmin(d)]) if d.min() < 0.3 else -1)
    ids = np.array(out)
    dup = [k for k in set(ids) if k >= 0 and np.sum(ids == k) > 1]
    ids[np.isin(ids, dup)] = -1                       # ambiguous: no match
    return ids


def _corner_depth(rng, intr, camera_xy=(0.0, 0.0), noise_per_m2=0.0, block=3):
    """Depth image (m) of a level camera 1.4 m above the floor, facing a wall 5 m ahead,
    another 2 m to its right, moved ``camera_xy`` (right, forward); depth noise of std
    ``noise_per_m2`` x z^2 in blocks of ``block`` pixels (as an active-stereo camera's)."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(float)
    dx, dy = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    z = np.full(dx.shape, 5.0 - camera_xy[1])
    z = np.where(dy > 1e-6, np.minimum(z, 1.4 / np.maximum(dy, 1e-6)), z)
    z = np.where(dx > 1e-6, np.minimum(z, (2.0 - camera_xy[0]) / np.maximum(dx, 1e-6)), z)
    noise = np.kron(rng.normal(0, 1, (intr.height // block + 1, intr.width // block + 1)), np.ones((block, block)))
    return (z + noise_per_m2 * z ** 2 * noise[:intr.height, :intr.width]).astype(np.float32)


def test_noisy_walls_far_away_are_surfaces_that_fix_the_camera():
    """Depth noise of 3.8 cm at 5 m (an active-stereo camera) turns the far walls into slabs a
    few 12 cm cells thick: the ten nearest points of most wall points form no surface (0.37 of
    them usable that way), and a frame seeing the floor and the walls would leave a horizontal
    direction free. Their thirty nearest do form one: the walls are kept and fix the camera."""
    intr = CameraIntrinsics(380.0, 380.0, 320.0, 240.0, 640, 480)
    rng = np.random.default_rng(0)
    clouds = [depth_cloud(_corner_depth(rng, intr, xy, noise_per_m2=0.0015), intr, [0.0, 1.0, 0.0], 0.12, 6.0)
              for xy in ((0.0, 0.0), (0.1, -0.15))]
    index = PointIndex(clouds[0])
    walls = clouds[0][:, 2] > -1.2                                  # off the floor (z up, 1.4 m below)
    assert index.usable[walls].mean() > 0.8 and index.usable[~walls].mean() > 0.7
    found = align_points(Pose4(0.0, (0.0, 0.0, 0.0)), clouds[1], index)
    assert found is not None and found.free == 0
    # the second camera 10 cm right of and 15 cm behind the first: (x forward, y left)
    assert np.linalg.norm(np.asarray(found.pose.t[:2]) - (-0.15, -0.1)) < 0.03, found.pose.t


def test_a_look_alike_placement_puts_surfaces_in_space_the_other_view_saw_through():
    """Pairs of rendered views 1.2 s apart through the depth detector: placed where they
    were taken, few of the points either moves into the other's view lie in space that view
    saw through (depth noise, edges); moved 1 m as a look-alike of three objects would
    place them (the yaw right), many do."""
    cap = Capture(CaptureConfig(seed=44, frames=40, fps=10.0, room_style='textured'))
    frames = list(cap.frames())
    det = make_detector('depth_clusters')
    obs = [det.detect(f.detector_input()) for f in frames]
    right, shifted = [], []
    for i in range(0, 28, 3):
        a, b = obs[i], obs[i + 12]
        truth = (frames[i].aligned_from_map() @ frames[i + 12].aligned_from_map().inverse()).matrix()   # T_a_b
        for out, offset in ((right, (0.0, 0.0)), (shifted, (1.0, 0.0)), (shifted, (0.0, 1.0))):
            t_a_b = truth.copy()
            t_a_b[:2, 3] += offset
            points, through = seen_through_both(a.cloud, a.rotation_aligned_from_camera, b.cloud,
                                                b.rotation_aligned_from_camera, t_a_b)
            assert points >= 50                   # the two views overlap
            out.append(through / points)
    assert max(right) < 0.05, right
    assert np.median(shifted) > 0.1 and np.mean(np.array(shifted) > 0.05) > 0.8, shifted
