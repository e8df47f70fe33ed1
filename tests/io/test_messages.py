"""rfm_core.io.messages: core types <-> rfm_msgs / geometry_msgs."""
import numpy as np
import pytest

pytest.importorskip('rfm_msgs.msg')

from rfm_core.geometry import (  # noqa: E402
    BOX_EDGES, Pose4, box_corners, gravity_aligned_rotation, matrix_from_quaternion,
)
from rfm_core.io.messages import (  # noqa: E402
    box_markers_msg, frame_detections_from_msg, frame_detections_to_msg, matrix_to_pose, ns_to_stamp,
    pose4_to_pose, pose_to_matrix, pose_to_pose4, stamp_to_ns,
)
from rfm_core.observations import CameraIntrinsics, FrameObservations  # noqa: E402


def make_observations(rng, n=4, gravity=(0.1, 0.95, -0.2)):
    return FrameObservations(
        stamp_ns=1_700_000_000_123_456_789,
        frame_id='camera_color_optical_frame',
        intrinsics=CameraIntrinsics(500.0, 505.0, 320.5, 240.5, 640, 480),
        gravity_cam=np.array(gravity),
        boxes=np.c_[rng.uniform(-2, 2, (n, 3)), rng.uniform(0.2, 2, (n, 3)),
                    rng.uniform(-3, 3, n)],
        scores=rng.uniform(0, 1, n),
        labels=[f'class{i}' for i in range(n)],
        embeddings=rng.normal(size=(n, 16)),
        boxes_2d=rng.uniform(0, 400, (n, 4)),
        visibility=rng.uniform(0, 1, n),
        object_ids=np.arange(n) + 10,
        corner_descriptors=rng.normal(size=(n, 8, 3)),
        full_boxes=np.c_[rng.uniform(-2, 2, (n, 3)), rng.uniform(0.2, 2, (n, 3)), rng.uniform(-3, 3, n)],
        backend='ground_truth',
        camera_height=1.47,
        walls=[[0.6, 0.8, 2.5], [-0.8, 0.6, 1.2]],
        cloud=rng.uniform(-3, 3, (50, 3)),
    )


def test_stamps_round_trip():
    assert stamp_to_ns(ns_to_stamp(1_700_000_000_999_999_999)) == 1_700_000_000_999_999_999


def test_pose_conversions_round_trip():
    rng = np.random.default_rng(0)
    m = np.eye(4)
    m[:3, :3] = matrix_from_quaternion(rng.normal(size=4))
    m[:3, 3] = rng.normal(size=3)
    np.testing.assert_allclose(pose_to_matrix(matrix_to_pose(m)), m, atol=1e-12)
    p = Pose4(-2.0, (1.0, 2.0, 3.0))
    back = pose_to_pose4(pose4_to_pose(p))
    assert back.angle_to(p) < 1e-12 and np.allclose(back.t, p.t)


def test_frame_detections_round_trip_preserves_everything():
    obs = make_observations(np.random.default_rng(1))
    msg = frame_detections_to_msg(obs)
    assert msg.header.frame_id == obs.frame_id and len(msg.detections) == 4
    back = frame_detections_from_msg(msg)
    assert back.stamp_ns == obs.stamp_ns and back.backend == 'ground_truth'
    assert back.intrinsics == obs.intrinsics
    np.testing.assert_allclose(back.gravity_cam, obs.gravity_cam, atol=1e-12)
    # boxes may come back with the equivalent yaw; compare corners as sets
    for a, b in zip(np.r_[back.boxes, back.full_boxes], np.r_[obs.boxes, obs.full_boxes]):
        ca, cb = box_corners(a), box_corners(b)
        np.testing.assert_allclose(ca[np.lexsort(ca.T)], cb[np.lexsort(cb.T)], atol=1e-6)
    np.testing.assert_allclose(back.scores, obs.scores, rtol=1e-6)
    assert back.labels == obs.labels
    np.testing.assert_allclose(back.embeddings, obs.embeddings, rtol=1e-6)
    np.testing.assert_allclose(back.corner_descriptors, obs.corner_descriptors, rtol=1e-6)
    np.testing.assert_allclose(back.boxes_2d, obs.boxes_2d, rtol=1e-6)
    np.testing.assert_array_equal(back.object_ids, obs.object_ids)
    assert back.camera_height == pytest.approx(1.47)
    np.testing.assert_allclose(back.walls, obs.walls, atol=1e-9)
    np.testing.assert_allclose(back.cloud, obs.cloud, atol=1e-5)


def test_depth_points_travel_in_the_optical_frame_and_are_validated():
    """The cloud travels as x y z triplets in the optical frame and comes back in the
    gravity-aligned frame; a length that is not triplets, a non-finite value or too many
    points is refused."""
    obs = make_observations(np.random.default_rng(4))
    msg = frame_detections_to_msg(obs)
    optical = np.asarray(msg.cloud, np.float64).reshape(-1, 3)
    np.testing.assert_allclose(optical @ gravity_aligned_rotation(obs.gravity_cam).T, obs.cloud, atol=1e-5)
    msg.cloud = []
    assert frame_detections_from_msg(msg).cloud.shape == (0, 3)     # none (older rfm versions, no depth)
    for spoil, match in [(lambda m: m.cloud.pop(), 'triplets'),
                         (lambda m: m.cloud.__setitem__(4, float('inf')), 'finite'),
                         (lambda m: m.cloud.extend([0.5] * 3 * 20_000), 'at most')]:
        m = frame_detections_to_msg(obs)
        m.cloud = list(m.cloud)
        spoil(m)
        with pytest.raises(ValueError, match=match):
            frame_detections_from_msg(m)


def test_walls_are_planes_in_the_optical_frame_and_validated():
    """Walls travel as optical-frame normals and distances; a message with mismatched lists,
    a non-finite or zero normal, a normal along gravity or too many walls is refused."""
    obs = make_observations(np.random.default_rng(3))
    msg = frame_detections_to_msg(obs)
    assert len(msg.wall_normals) == len(msg.wall_distances) == 2
    n = np.array([msg.wall_normals[0].x, msg.wall_normals[0].y, msg.wall_normals[0].z])
    assert abs(n @ obs.gravity_cam) < 1e-9                        # vertical planes: normals across gravity
    np.testing.assert_allclose(gravity_aligned_rotation(obs.gravity_cam) @ n, [0.6, 0.8, 0.0], atol=1e-9)
    none = frame_detections_to_msg(make_observations(np.random.default_rng(3)).subset([0]))
    none.wall_normals, none.wall_distances = [], []
    assert frame_detections_from_msg(none).walls.shape == (0, 3)
    bad = [('wall_distances', lambda m: m.wall_distances.pop(), 'wall normals for'),
           ('nan', lambda m: setattr(m.wall_normals[0], 'x', float('nan')), 'finite'),
           ('zero', lambda m: [setattr(m.wall_normals[0], a, 0.0) for a in 'xyz'], 'finite'),
           ('along gravity', lambda m: [setattr(m.wall_normals[0], a, float(v))
                                        for a, v in zip('xyz', obs.gravity_cam)], 'perpendicular'),
           ('negative distance', lambda m: m.wall_distances.__setitem__(0, -1.0), 'walls'),
           ('too many', lambda m: (m.wall_normals.extend([m.wall_normals[0]] * 70),
                                   m.wall_distances.extend([2.0] * 70)), 'at most')]
    for name, spoil, match in bad:
        m = frame_detections_to_msg(obs)
        m.wall_distances = list(m.wall_distances)
        spoil(m)
        with pytest.raises(ValueError, match=match):
            frame_detections_from_msg(m)


def test_a_camera_height_not_measured_reads_as_unknown():
    """0 (the message default: older rfm versions, hand-made messages), NaN or a negative
    height is no measurement."""
    from dataclasses import replace
    obs = replace(make_observations(np.random.default_rng(2)), camera_height=float('nan'))
    msg = frame_detections_to_msg(obs)
    assert msg.camera_height == 0.0
    assert np.isnan(frame_detections_from_msg(msg).camera_height)
    for value in (float('nan'), float('inf'), -1.2):
        msg.camera_height = value
        assert np.isnan(frame_detections_from_msg(msg).camera_height)


def test_full_boxes_are_optional_but_all_or_none():
    """Detections without full boxes (every backend but depth_clusters' refiner, and messages
    of older rfm versions) read as boxes that are their own full boxes; a message giving them
    for some detections only is refused."""
    from dataclasses import replace
    obs = replace(make_observations(np.random.default_rng(4)), full_boxes=None)
    back = frame_detections_from_msg(frame_detections_to_msg(obs))
    assert back.full_boxes is None and back.map_boxes is back.boxes
    msg = frame_detections_to_msg(make_observations(np.random.default_rng(4)))
    assert len(msg.detections[0].full_pose) == len(msg.detections[0].full_size) == 1
    msg.detections[2].full_pose, msg.detections[2].full_size = [], []
    with pytest.raises(ValueError, match='full_pose'):
        frame_detections_from_msg(msg)
    with pytest.raises(ValueError, match='full_boxes'):
        replace(obs, full_boxes=np.zeros((3, 7)))


def test_oversized_messages_are_refused_before_any_work():
    """10k detections blocked the matcher and mapper for minutes (#19 row 7); huge
    embeddings likewise."""
    from rfm_core.io.messages import MAX_DESCRIPTOR_DIM, MAX_DETECTIONS
    rng = np.random.default_rng(5)
    msg = frame_detections_to_msg(make_observations(rng, n=MAX_DETECTIONS + 1))
    with pytest.raises(ValueError, match=f'at most {MAX_DETECTIONS}'):
        frame_detections_from_msg(msg)
    assert len(frame_detections_from_msg(frame_detections_to_msg(make_observations(rng, n=MAX_DETECTIONS)))) \
        == MAX_DETECTIONS
    msg = frame_detections_to_msg(make_observations(rng, n=3))
    for det in msg.detections:
        det.embedding = np.ones(MAX_DESCRIPTOR_DIM + 1, np.float32)
    with pytest.raises(ValueError, match='longer than'):
        frame_detections_from_msg(msg)


def test_boxes_are_published_in_the_camera_optical_frame():
    obs = make_observations(np.random.default_rng(2), n=1, gravity=(0.0, 1.0, 0.0))
    obs.boxes[0] = [3.0, 0.5, -0.2, 1.0, 2.0, 0.5, 0.0]  # 3 m ahead, 0.5 m left, 0.2 m down
    det = frame_detections_to_msg(obs).detections[0]
    np.testing.assert_allclose([det.pose.position.x, det.pose.position.y, det.pose.position.z],
                               [-0.5, 0.2, 3.0], atol=1e-12)
    # box's local z (vertical) points "up" = -y in the optical frame
    rot = pose_to_matrix(det.pose)[:3, :3]
    np.testing.assert_allclose(rot[:, 2], [0, -1, 0], atol=1e-12)
    assert gravity_aligned_rotation(obs.gravity_cam) @ rot[:, 2] == pytest.approx([0, 0, 1])


def test_invalid_messages_raise_clear_errors():
    msg = frame_detections_to_msg(make_observations(np.random.default_rng(3)))
    msg.fx = 0.0
    with pytest.raises(ValueError, match='fx'):
        frame_detections_from_msg(msg)
    msg = frame_detections_to_msg(make_observations(np.random.default_rng(3)))
    msg.gravity.x = msg.gravity.y = msg.gravity.z = 0.0
    with pytest.raises(ValueError, match='gravity'):
        frame_detections_from_msg(msg)
    msg = frame_detections_to_msg(make_observations(np.random.default_rng(3)))
    msg.detections[1].embedding = [1.0, 2.0]
    with pytest.raises(ValueError, match='embeddings of different lengths'):
        frame_detections_from_msg(msg)
    msg = frame_detections_to_msg(make_observations(np.random.default_rng(3)))
    msg.detections[0].pose.orientation.w = 0.0
    msg.detections[0].pose.orientation.x = 0.0
    msg.detections[0].pose.orientation.y = 0.0
    msg.detections[0].pose.orientation.z = 0.0
    with pytest.raises(ValueError, match='quaternion'):
        frame_detections_from_msg(msg)
    msg = frame_detections_to_msg(make_observations(np.random.default_rng(3)))
    msg.detections[2].size.x = -1.0
    with pytest.raises(ValueError, match='size'):
        frame_detections_from_msg(msg)
    # NaN / inf in what the matchers and averaging compute with (it killed the mapper: #19)
    for field, says in (('embedding', 'embeddings'), ('score', 'scores'), ('box_2d', '2D boxes')):
        msg = frame_detections_to_msg(make_observations(np.random.default_rng(3)))
        value = getattr(msg.detections[1], field)
        setattr(msg.detections[1], field, float('inf') if field == 'score' else [float('nan')] * len(value))
        with pytest.raises(ValueError, match=f'{says} must be finite'):
            frame_detections_from_msg(msg)


def test_observations_validate_lengths_and_fill_optional_fields():
    intr = CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    obs = FrameObservations(0, 'cam', intr, [0, 1, 0], boxes=np.zeros((2, 7)), scores=[0.5, 0.6])
    assert obs.labels == ['', ''] and obs.embeddings.shape == (2, 0)
    assert list(obs.object_ids) == [-1, -1] and list(obs.visibility) == [-1, -1]
    with pytest.raises(ValueError, match='scores has 1 entries for 2 boxes'):
        FrameObservations(0, 'cam', intr, [0, 1, 0], boxes=np.zeros((2, 7)), scores=[0.5])
    with pytest.raises(ValueError, match='image size'):
        CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 0, 480)


def test_box_markers_draw_every_edge_and_label_each_box():
    """One DELETEALL, then per box a LINE_LIST through its 12 edges and a facing label."""
    boxes = np.array([[1.0, 2.0, 0.5, 0.4, 0.6, 1.0, 0.3], [-1.0, 0.0, 0.2, 1.0, 1.0, 0.4, 0.0]])
    corners = box_corners(boxes)
    msg = box_markers_msg(corners, ['chair 0.90', 'table 0.50'], boxes[:, :3], [(1, 0, 0, 1), (0, 1, 0, 1)],
                          1_500_000_000, 'map', ids=[7, 9], text_colour=(1, 1, 1, 1))
    clear, *rest = msg.markers
    assert clear.action == clear.DELETEALL and clear.header.frame_id == 'map'
    lines, texts = rest[0::2], rest[1::2]
    assert [m.id for m in lines] == [7, 9] and all(m.type == m.LINE_LIST for m in lines)
    assert all(m.type == m.TEXT_VIEW_FACING for m in texts) and [m.text for m in texts] == ['chair 0.90', 'table 0.50']
    for m, c in zip(lines, corners):
        points = np.array([[p.x, p.y, p.z] for p in m.points]).reshape(12, 2, 3)
        assert np.allclose(points, c[BOX_EDGES])                    # each edge joins its two corners
        assert m.header.stamp.sec == 1 and m.header.stamp.nanosec == 500_000_000
    assert texts[1].pose.position.x == -1.0 and texts[0].color.g == 1.0 and lines[1].color.g == 1.0
    assert len(box_markers_msg(np.zeros((0, 8, 3)), [], np.zeros((0, 3)), [], 0, 'map').markers) == 1
