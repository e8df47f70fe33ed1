"""rfm_core.sim: rooms, trajectories, rendering and ground truth against independent checks."""
import numpy as np
import pytest

from rfm_core.geometry import box_corners, yaw_matrix
from rfm_core.sim.capture import Capture, CaptureConfig
from rfm_core.sim.render import NoiseModel
from rfm_core.sim.room import generate_room
from rfm_core.sim.trajectory import GRAVITY, imu_samples, look_rotation, make_trajectory


@pytest.fixture(scope='module')
def capture():
    cap = Capture(CaptureConfig(seed=11, room_style='textured', frames=12, fps=5,
                                noise=NoiseModel.none()))
    return cap, list(cap.frames())


def test_rooms_are_furnished_and_deterministic():
    counts, groups, stacked = [], 0, 0
    for seed in range(12):
        room = generate_room(seed, 'plain' if seed % 2 else 'textured')
        counts.append(len(room.objects))
        assert np.all(room.boxes[:, 3:6] > 0)
        # every object inside the room, standing on the floor or on another object
        corners = box_corners(room.boxes)
        assert np.all(corners >= -1e-6) and np.all(corners <= room.size + 1e-6)
        tops = room.boxes[:, 2] + room.boxes[:, 5] / 2
        for box in room.boxes:
            bottom = box[2] - box[5] / 2
            on_floor = abs(bottom) < 1e-9
            on_support = np.any(np.abs(tops - bottom) < 1e-9)
            assert on_floor or on_support
            stacked += on_support and not on_floor
        labels = room.labels
        by_group = {}
        for obj in room.objects:
            if obj.group >= 0:
                by_group.setdefault(obj.group, []).append(obj)
        for members in by_group.values():          # identical copies: same size and colour
            assert len({tuple(np.round(m.box[3:6], 9)) for m in members}) == 1
            assert len({m.material.color for m in members}) == 1
        groups += sum(len(m) > 1 for m in by_group.values())
        assert len(set(labels)) >= 3
    assert min(counts) >= 10 and max(counts) <= 40
    assert groups >= 12 and stacked >= 24          # identical groups and small objects on top
    a, b = generate_room(5, 'plain'), generate_room(5, 'plain')
    np.testing.assert_array_equal(a.boxes, b.boxes)


def test_trajectories_stay_in_free_space():
    room = generate_room(3, 'plain')
    handheld = make_trajectory(room, 'handheld', 90, fps=30, seed=1)
    assert not any(room.contains_camera(p) for p in handheld.positions)
    steps = np.linalg.norm(np.diff(handheld.positions, axis=0), axis=1)
    assert np.all(steps < 0.05) and np.all(steps > 0.001)          # smooth walk at ~0.35 m/s
    np.testing.assert_allclose(np.diff(handheld.times), 1 / 30)
    sparse = make_trajectory(room, 'sparse', 20, seed=2)
    assert not any(room.contains_camera(p, margin=0.25) for p in sparse.positions)
    assert np.median(np.linalg.norm(np.diff(sparse.positions, axis=0), axis=1)) > 0.5
    for traj in (handheld, sparse, make_trajectory(room, 'orbit', 30, seed=3)):
        rots = traj.rotations
        np.testing.assert_allclose(rots @ np.transpose(rots, (0, 2, 1)), np.broadcast_to(np.eye(3), rots.shape), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(rots), 1.0)


def test_imu_reads_gravity_along_up_in_the_camera_frame():
    room = generate_room(3, 'plain')
    traj = make_trajectory(room, 'handheld', 60, fps=30, seed=1)
    imu = imu_samples(traj, 200.0, seed=0)
    assert len(imu.times) == int(traj.times[-1] * 200) + 1
    # the camera's "up" in its own frame is R^T z; the specific force points along it
    frames = np.clip(np.round(imu.times * 30).astype(int), 0, len(traj) - 1)
    up_cam = np.einsum('nji,j->ni', traj.rotations[frames], [0.0, 0.0, 1.0])
    cosine = np.sum(imu.linear_acceleration * up_cam, axis=1) / np.linalg.norm(imu.linear_acceleration, axis=1)
    assert np.median(cosine) > 0.995
    assert abs(np.median(np.linalg.norm(imu.linear_acceleration, axis=1)) - GRAVITY) < 0.2


def test_the_imu_of_a_photo_collection_sees_the_turns_between_the_photos():
    """The photographer carries the camera from one viewpoint to the next: the gyroscope,
    integrated (by the gravity filter), turns by what the photos turned, and the camera is
    still at each photo (the accelerometer reads gravity alone)."""
    from scipy.spatial.transform import Rotation

    from rfm_core.detection.gravity import GravityFilter
    traj = make_trajectory(generate_room(3, 'plain'), 'sparse', 12, seed=2, sparse_gap_s=(1.5, 5.0))
    imu = imu_samples(traj, 200.0, seed=0)
    gravity, orientations = GravityFilter(), []
    for t, force, omega in zip(imu.times, imu.linear_acceleration, imu.angular_velocity):
        gravity.add(int(round(t * 1e9)), force, omega)
        if len(orientations) < len(traj) and t > traj.times[len(orientations)] - 0.005:     # the photo's sample
            orientations.append(gravity.orientation_at(int(round(t * 1e9))))
    turns, errors = [], []
    for k in range(len(traj) - 1):
        (a, epoch_a), (b, epoch_b) = orientations[k], orientations[k + 1]
        truth = traj.rotations[k].T @ traj.rotations[k + 1]
        turns.append(np.degrees(Rotation.from_matrix(truth).magnitude()))
        if epoch_a == epoch_b:
            errors.append(np.degrees(Rotation.from_matrix((a.T @ b).T @ truth).magnitude()))
    assert np.median(turns) > 20.0                          # the photos face all ways
    assert len(errors) >= len(turns) - 3 and max(errors) < 0.5
    at_photos = np.searchsorted(imu.times, traj.times - 0.005)
    up = np.einsum('nji,j->ni', traj.rotations, [0.0, 0.0, GRAVITY])
    np.testing.assert_allclose(imu.linear_acceleration[at_photos], up, atol=0.1)


def ray_box_depth(rotation, position, intrinsics, u, v, box):
    """z-depth where the pixel's ray enters ``box``, by an independent slab test."""
    d_cam = np.array([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, 1.0])
    d = yaw_matrix(-box[6]) @ (rotation @ d_cam)
    o = yaw_matrix(-box[6]) @ (position - box[:3])
    with np.errstate(divide='ignore'):
        t1, t2 = (-box[3:6] / 2 - o) / d, (box[3:6] / 2 - o) / d
    near, far = np.max(np.minimum(t1, t2)), np.min(np.maximum(t1, t2))
    return near if near <= far and near > 0 else np.inf


def test_depth_agrees_with_ray_box_distances(capture):
    cap, frames = capture
    rng = np.random.default_rng(0)
    checked = 0
    for frame in frames[::3]:
        inst = frame.render.instance
        ys, xs = np.nonzero(inst > 0)
        for i in rng.choice(len(ys), 60, replace=False):
            k = inst[ys[i], xs[i]] - 1
            expected = ray_box_depth(frame.rotation, frame.position, cap.intrinsics, xs[i], ys[i],
                                     cap.room.boxes[k])
            assert frame.render.depth_true[ys[i], xs[i]] == pytest.approx(expected, rel=1e-4)
            checked += 1
    assert checked == 240


def test_ground_truth_boxes_project_onto_instance_masks(capture):
    cap, frames = capture
    intr = cap.intrinsics
    ious = []
    for frame in frames:
        gt = frame.ground_truth
        aligned_from_cam = gt.rotation_aligned_from_camera
        for box, oid in zip(gt.boxes, gt.object_ids):
            k = oid - 1
            r = frame.render
            if r.visible_pixels[k] != r.unoccluded_pixels[k] or r.visible_pixels[k] < 200:
                continue                                 # occluded or tiny
            cam = box_corners(box) @ aligned_from_cam     # gravity-aligned -> camera optical
            if np.any(cam[:, 2] <= 0.05):
                continue
            uv = np.c_[intr.fx * cam[:, 0] / cam[:, 2] + intr.cx, intr.fy * cam[:, 1] / cam[:, 2] + intr.cy]
            if np.any(uv < 0) or np.any(uv[:, 0] > intr.width - 1) or np.any(uv[:, 1] > intr.height - 1):
                continue                                 # truncated by the image border
            ys, xs = np.nonzero(r.instance == oid)
            mask_box = np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])
            proj = np.r_[uv.min(0), uv.max(0)]
            inter = np.prod(np.clip(np.minimum(proj[2:], mask_box[2:]) - np.maximum(proj[:2], mask_box[:2]), 0, None))
            union = np.prod(proj[2:] - proj[:2]) + np.prod(mask_box[2:] - mask_box[:2]) - inter
            ious.append(inter / union)
            assert gt.visibility[list(gt.object_ids).index(oid)] > 0.9
    assert len(ious) >= 10
    assert np.mean(ious) > 0.8


def test_ground_truth_lists_the_visible_objects_with_their_visible_fraction(capture):
    cap, frames = capture
    for frame in frames:
        gt, r = frame.ground_truth, frame.render
        visible_ids = set(np.flatnonzero(r.visible_pixels >= 0.001 * 320 * 240) + 1)
        assert set(gt.object_ids) == visible_ids
        for oid, vis in zip(gt.object_ids, gt.visibility):
            assert 0 < vis <= 1
            assert vis <= r.visible_pixels[oid - 1] / max(r.unoccluded_pixels[oid - 1], 1) + 1e-6


def test_noise_model_holes_and_error_grow_with_distance():
    cap = Capture(CaptureConfig(seed=4, frames=3, fps=5))
    frame = next(cap.frames())
    true, noisy = frame.render.depth_true, frame.render.depth
    holes = np.isnan(noisy)
    assert 0.002 < holes.mean() < 0.1
    err = np.abs(noisy - true)[~holes]
    near = err[true[~holes] < 2.0]
    far = err[true[~holes] > 4.0]
    assert np.median(near) < 0.01 and np.median(far) > np.median(near)
    assert frame.render.rgb.std() > 10


# ---------------------------------------------------------------- furniture made of parts, clutter

def _look_at(eye, target):
    return look_rotation(np.asarray(target, float) - eye)     # camera-to-map rotation


def _one_object_room(label, size, furniture):
    from rfm_core.sim.furniture import object_parts
    from rfm_core.sim.room import Material, Room, RoomObject
    paint = Material((0.8, 0.8, 0.8))
    box = np.array([3.0, 2.5, size[2] / 2, *size, 0.0])
    parts = object_parts(label, size) if furniture == 'parts' else None
    return Room(size=np.array([6.0, 5.0, 2.8]), walls=(paint,) * 6,
                objects=[RoomObject(box, label, Material((0.5, 0.3, 0.2)), parts=parts)])


def test_a_tables_legs_are_hit_under_its_top_and_the_space_between_them_is_seen_through():
    from rfm_core.sim.render import Renderer
    intr = CaptureConfig(width=160, height=120).intrinsics
    eye = np.array([3.0, 0.6, 0.3])                  # low, looking along +y under the table top
    depth_rows = {}
    for furniture in ('boxes', 'parts'):
        room = _one_object_room('table', (1.2, 0.8, 0.75), furniture)
        out = Renderer(room, intr, NoiseModel.none()).render(_look_at(eye, [3.0, 2.5, 0.3]), eye)
        row = out.instance[intr.height // 2]          # the image row at the camera's height
        depth_rows[furniture] = (row, out.depth_true[intr.height // 2])
    solid, parts = depth_rows['boxes'], depth_rows['parts']
    assert np.all(solid[0][70:90] == 1)                 # the solid box fills the view's middle
    # with parts: the two front legs are hit, the middle of the row sees the far wall
    hit = np.flatnonzero(parts[0] == 1)
    assert len(hit) > 2 and hit.min() < 60 and hit.max() > 100
    middle = slice(72, 88)
    assert np.all(parts[0][middle] == 0) and np.all(parts[1][middle] > 4.0)        # the wall at y = 5
    assert np.all(solid[1][middle] < 2.5)


def test_parts_keep_the_layout_and_the_amodal_ground_truth():
    boxes = Capture(CaptureConfig(seed=21, frames=3))
    parts = Capture(CaptureConfig(seed=21, frames=3, furniture='parts', clutter=True))
    n = len(boxes.room.objects)
    # the same furniture in the same places; open shelves may get objects on their boards
    assert np.array_equal(parts.room.boxes[:n], boxes.room.boxes)
    extra = parts.room.objects[n:]
    assert all(o.label in ('books', 'box', 'vase') for o in extra)
    labels_with_parts = {o.label for o in parts.room.objects if o.parts is not None}
    assert labels_with_parts and labels_with_parts <= {'table', 'desk', 'chair', 'stool', 'bookshelf', 'sofa',
                                                       'armchair', 'bed', 'lamp', 'plant'}
    for obj in parts.room.objects:                     # every part inside its object's box
        if obj.parts is not None:
            corners = box_corners(obj.parts)
            assert np.all(np.abs(corners) <= obj.box[3:6] / 2 + 1e-9), obj.label
    frame = next(parts.frames())
    gt = frame.ground_truth
    assert set(gt.object_ids) <= set(range(1, len(parts.room.objects) + 1))      # clutter is no object
    # deterministic
    again = Capture(CaptureConfig(seed=21, frames=3, furniture='parts', clutter=True))
    assert np.array_equal(next(again.frames()).render.rgb, frame.render.rgb)


def test_clutter_is_rendered_but_in_no_ground_truth():
    from rfm_core.sim.furniture import Clutter
    from rfm_core.sim.render import Renderer
    from rfm_core.sim.room import Material
    room = _one_object_room('cabinet', (0.8, 0.5, 1.0), 'boxes')
    intr = CaptureConfig(width=160, height=120).intrinsics
    eye = np.array([3.0, 1.0, 1.5])
    view = _look_at(eye, [3.0, 5.0, 1.6])               # at the far wall, above the cabinet
    before = Renderer(room, intr, NoiseModel.none()).render(view, eye)
    room.clutter = [Clutter([3.0, 4.985, 1.6, 0.8, 0.03, 0.6, np.pi], 'picture', Material((0.9, 0.1, 0.1)))]
    after = Renderer(room, intr, NoiseModel.none()).render(view, eye)
    changed = np.abs(after.depth_true - before.depth_true) > 0.01
    assert changed.sum() > 200                          # the picture stands out of the wall ...
    assert np.all(after.instance[changed] == 0)         # ... and belongs to no object
    assert np.array_equal(after.visible_pixels, before.visible_pixels)
    assert np.any(after.rgb[changed][:, 0] > 2 * after.rgb[changed][:, 1])          # it is red


def test_realsense_depth_has_projector_shadows_flying_pixels_and_dark_dropouts():
    from rfm_core.sim.render import Renderer
    intr = CaptureConfig(width=320, height=240).intrinsics
    room = _one_object_room('cabinet', (0.6, 0.5, 1.6), 'boxes')       # a tall box 3 m in front of a wall
    eye = np.array([3.0, 1.0, 0.8])
    view = _look_at(eye, [3.0, 5.0, 0.8])
    row = intr.height // 2
    rng = np.random.default_rng(3)
    clean = Renderer(room, intr, NoiseModel.none()).render(view, eye)
    default = Renderer(room, intr, NoiseModel()).render(view, eye, np.random.default_rng(3))
    stereo = Renderer(room, intr, NoiseModel.realsense()).render(view, eye, rng)
    cols = np.flatnonzero(clean.instance[row] == 1)
    left = cols.min()                                   # the box's left edge in this row
    z_near, z_far = clean.depth_true[row, left], clean.depth_true[row, left - 1]
    band = intr.fx * 0.025 * (1 / z_near - 1 / z_far)                  # the projector's parallax (px)
    assert band > 2
    shadow = slice(left - int(band) + 1, left)
    rows = slice(row - 10, row + 10)
    assert np.all(np.isnan(stereo.depth[rows, shadow]))                 # the background beside the edge
    assert np.mean(np.isnan(default.depth[rows, shadow])) < 0.5         # today's model has no shadow
    # away from edges the depth noise grows with range^2: about 1 cm at 2 m
    wall = stereo.depth[rows, 5:left - 8] - clean.depth_true[rows, 5:left - 8]
    near = stereo.depth[rows, left + 3:cols.max() - 3] - clean.depth_true[rows, left + 3:cols.max() - 3]
    assert 0.002 < np.nanstd(near) < 0.02 and np.nanstd(wall) > 2 * np.nanstd(near)
    # depth is lost on a dark surface
    from rfm_core.sim.room import Material
    dark = _one_object_room('cabinet', (0.6, 0.5, 1.6), 'boxes')
    dark.objects[0] = type(dark.objects[0])(dark.objects[0].box, 'cabinet', Material((0.05, 0.05, 0.05)))
    out = Renderer(dark, intr, NoiseModel.realsense()).render(view, eye, np.random.default_rng(4))
    on_box = out.instance == 1
    assert np.mean(np.isnan(out.depth[on_box])) > 0.5 > np.mean(np.isnan(stereo.depth[stereo.instance == 1]))


def test_capture_timing_heights_and_a_robots_level_camera():
    sparse = Capture(CaptureConfig(seed=3, capture='sparse', frames=12, sparse_gap_s=(2.0, 6.0)))
    gaps = np.diff(sparse.trajectory.times)
    assert np.all((gaps >= 2.0) & (gaps <= 6.0)) and np.ptp(gaps) > 1.0           # irregular photos
    assert np.array_equal(Capture(CaptureConfig(seed=3, capture='sparse', frames=5)).trajectory.times,
                          np.arange(5.0))                                           # the default: 1 s
    low = Capture(CaptureConfig(seed=3, frames=20, fps=15, camera_height=(1.0, 1.05)))
    assert np.all(np.abs(low.trajectory.positions[:, 2] - 1.025) < 0.1)
    assert np.allclose(np.diff(low.trajectory.times), 1 / 15)
    robot = Capture(CaptureConfig(seed=3, capture='robot', frames=300, fps=10, furniture='parts'))
    z = robot.trajectory.positions[:, 2]
    assert 0.3 <= z.min() and z.max() <= 0.9 and np.ptp(z) < 1e-9                    # on a base
    rot = robot.trajectory.rotations
    assert np.allclose(rot[:, 2, 0], 0, atol=1e-9) and np.allclose(rot[:, 2, 2], 0, atol=1e-9)  # level
    # a wheeled base: it turns in place and drives straight, at a robot's rates, clear of the furniture
    base = robot.trajectory.path.base(np.arange(0, 30, 0.02))
    speed = np.linalg.norm(np.diff(base[:, :2], axis=0), axis=1) / 0.02
    turn = np.degrees(np.abs(np.diff(base[:, 2]))) / 0.02
    assert speed.max() <= 0.5 + 1e-6 and turn.max() <= 45 * 1.01 and not np.any((speed > 0.01) & (turn > 0.01))
    assert np.sum(turn) * 0.02 > 90 and np.sum(speed) * 0.02 > 1.0
    assert not any(robot.room.contains_camera(p, margin=0.3) for p in robot.trajectory.positions)
    frame = next(robot.frames())
    assert frame.render.depth.shape == (240, 320) and len(frame.ground_truth) > 0


def test_an_outward_walk_circles_near_the_centre_looking_out_at_the_walls():
    """The relocalization protocol's other direction (and a second session's walk): near the
    room's centre, looking away from it, where a handheld walk looks across the room."""
    room = generate_room(3, 'plain')
    out = make_trajectory(room, 'outward', 40, fps=2, seed=1)
    across = make_trajectory(room, 'handheld', 40, fps=2, seed=1)
    centre = room.size[:2] / 2
    assert not any(room.contains_camera(p, margin=0.15) for p in out.positions)

    def facing_out(traj):
        away = traj.positions[:, :2] - centre
        forward = traj.rotations[:, :2, 2]
        return np.sum(away * forward, 1) / np.linalg.norm(away, axis=1) / np.linalg.norm(forward, axis=1)
    assert np.median(facing_out(out)) > 0.8 and np.median(facing_out(across)) < 0.3
    assert np.median(np.linalg.norm(out.positions[:, :2] - centre, axis=1)) < np.median(
        np.linalg.norm(across.positions[:, :2] - centre, axis=1))
    steps = np.linalg.norm(np.diff(out.positions, axis=0), axis=1)
    assert np.all(steps < 0.25)                                     # a slow walk: 0.25 m/s at 2 Hz
