"""Matching core: yaw-symmetry relabelling, classical matcher, relative pose + verification."""
import numpy as np
import pytest

from rfm_core.detection import make_detector
from rfm_core.geometry import Pose4, box_corners, iou_3d_paired, kabsch_4dof, wrap_angle
from rfm_core.matching.classical import ClassicalMatcher, ObjectMatches
from rfm_core.matching.config import MatchingConfig, monocular
from rfm_core.matching.corners import corner_permutation, quarter_turn_candidates, relabel
from rfm_core.matching.relative_pose import estimate_relative_pose
from rfm_core.sim.capture import Capture, CaptureConfig


def scene_boxes(rng, n):
    return np.c_[rng.uniform([-3, -3, -1.4], [3, 3, 0.5], (n, 3)), rng.uniform(0.2, 1.5, (n, 3)),
                 rng.uniform(-np.pi, np.pi, n)]


@pytest.mark.parametrize('k', range(4))
def test_relabel_describes_the_same_box_with_permuted_corners(k):
    box = np.array([1.0, 2.0, 0.5, 1.2, 0.4, 0.9, 0.3])
    other = relabel(box, k)
    np.testing.assert_allclose(box_corners(other), box_corners(box)[corner_permutation(k)], atol=1e-12)
    assert iou_3d_paired(box, other)[0] == pytest.approx(1.0)


def test_quarter_turns_respect_sizes():
    square = np.array([0, 0, 0, 0.5, 0.5, 1.0, 0.2])
    assert len(quarter_turn_candidates(square, relabel(square, 1), 0.2)) == 4
    long = np.array([0, 0, 0, 1.5, 0.5, 1.0, 0.2])
    ks = [k for k, _ in quarter_turn_candidates(long, relabel(long, 3), 0.2)]
    assert sorted(ks) == [1, 3]                 # only the turns that swap the sizes back


def transformed_scene(seed, n=10, noise=0.0):
    rng = np.random.default_rng(seed)
    a = scene_boxes(rng, n)
    truth = Pose4(rng.uniform(-np.pi, np.pi), rng.uniform(-2, 2, 3) * [1, 1, 0.1])
    b = truth.transform_boxes(a)
    # each detector reports its own yaw convention: random quarter turns
    b = np.stack([relabel(box, rng.integers(4)) for box in b])
    b[:, :3] += rng.normal(0, noise, (n, 3))
    b[:, 3:6] *= 1 + rng.normal(0, noise, (n, 3))
    return a, b, truth


@pytest.mark.parametrize('seed', range(5))
def test_recovers_a_known_relative_pose_despite_yaw_symmetries(seed):
    a, b, truth = transformed_scene(seed, noise=0.01)
    matches = ObjectMatches(np.arange(10), np.arange(10), np.ones(10))
    rel = estimate_relative_pose(a, b, matches)
    assert rel is not None
    assert np.degrees(rel.pose.angle_to(truth)) < 1.0
    assert np.linalg.norm(rel.pose.t - truth.t) < 0.03
    assert len(rel.inliers) == 10 and rel.inlier_ratio == 1.0
    assert len(rel.corner_inliers) >= 60        # most of the 80 corners within 10 cm


def test_along_ray_refit_for_monocular_detections():
    """Boxes whose distance is misjudged by a few percent in each frame (scaled about the
    camera, as a monocular detector errs) and one wrong match: the along-ray refit of a
    monocular config finds the relative pose clearly better than the default isotropic refit."""
    rng = np.random.default_rng(12)
    errors = {'default': [], 'monocular': []}
    for _ in range(60):
        truth = Pose4(rng.uniform(-0.6, 0.6), rng.uniform(-1, 1, 3) * [1, 1, 0.1])
        a = np.c_[rng.uniform([-2, -1.2, 1.5], [2, 0.3, 5], (6, 3)), rng.uniform(0.4, 1.2, (6, 3)),
                  rng.uniform(-np.pi, np.pi, 6)]
        b = truth.transform_boxes(a)
        frames = []
        for boxes in (a, b):
            scale = 1 + rng.normal(0, 0.03 + 0.01 * np.linalg.norm(boxes[:, :3], axis=1))
            noisy = boxes.copy()
            noisy[:, :6] *= scale[:, None]
            noisy[:, :3] += rng.normal(0, 0.02, (6, 3))
            frames.append(noisy)
        matches = ObjectMatches(np.arange(6), np.array([0, 1, 2, 3, 5, 4]), np.ones(6))  # 4 <-> 5 wrong
        for name, config in (('default', MatchingConfig()), ('monocular', monocular(MatchingConfig()))):
            rel = estimate_relative_pose(*frames, matches, config)
            if rel is not None:
                errors[name].append(np.linalg.norm(rel.pose.t - truth.t))
    assert len(errors['monocular']) >= 45
    assert np.median(errors['monocular']) < 0.8 * np.median(errors['default'])


def test_monocular_verification_forgives_a_misjudged_distance_not_a_wrong_place():
    """A small box reported 8% too far (scaled about the camera) in frame b no longer
    overlaps its match at IoU 0.25; a monocular config lets it slide back along the ray and
    counts it as an inlier. A box moved sideways by 40 cm stays an outlier either way."""
    truth = Pose4(0.3, (0.4, -0.2, 0.05))
    a = np.array([[-1.5, 0.2, 3.0, 0.8, 0.6, 0.7, 0.1], [1.4, 0.1, 3.5, 0.9, 0.5, 0.8, -0.4],
                  [0.0, 0.3, 4.0, 0.4, 0.4, 0.4, 0.0], [0.5, 0.3, 2.5, 0.4, 0.4, 0.4, 0.2],
                  [-0.6, 0.2, 2.0, 0.5, 0.5, 0.5, 0.0]])
    b = truth.transform_boxes(a)
    b[2, :6] *= 1.08                              # distance misjudged by 8%
    b[3, 0] += 0.4                                # a different place
    matches = ObjectMatches(np.arange(5), np.arange(5), np.ones(5))
    default = estimate_relative_pose(a, b, matches)
    mono = estimate_relative_pose(a, b, matches, monocular(MatchingConfig()))
    assert default is not None and mono is not None
    assert 2 not in default.inliers[:, 0] and 2 in mono.inliers[:, 0]
    assert 3 not in default.inliers[:, 0] and 3 not in mono.inliers[:, 0]
    assert np.degrees(mono.pose.angle_to(truth)) < 1.0 and np.linalg.norm(mono.pose.t - truth.t) < 0.05


def test_wrong_matches_are_outliers_and_random_matches_are_rejected():
    a, b, truth = transformed_scene(11, n=10, noise=0.01)
    wrong = np.arange(10)
    wrong[[0, 3, 6]] = wrong[[3, 6, 0]]                  # 30% wrong matches
    rel = estimate_relative_pose(a, b, ObjectMatches(np.arange(10), wrong, np.ones(10)))
    assert rel is not None and np.degrees(rel.pose.angle_to(truth)) < 1.0
    assert sorted(rel.inliers[:, 0].tolist()) == [1, 2, 4, 5, 7, 8, 9]
    rng = np.random.default_rng(3)
    c = scene_boxes(rng, 10)                             # an unrelated frame
    assert estimate_relative_pose(a, c, ObjectMatches(np.arange(10), rng.permutation(10), np.ones(10))) is None
    assert estimate_relative_pose(a, b, ObjectMatches(np.arange(1), np.arange(1), np.ones(1))) is None


def test_classical_matcher_and_pose_on_simulated_frames():
    cap = Capture(CaptureConfig(seed=30, frames=6, fps=3))
    frames = list(cap.frames())
    det = make_detector('ground_truth', preset='rgbd', seed=1)
    matcher = ClassicalMatcher()
    correct = total = verified = 0
    errors = []
    for f1, f2 in zip(frames[:-1], frames[1:]):
        o1, o2 = det.perturb(f1.ground_truth), det.perturb(f2.ground_truth)
        m = matcher.match(o1, o2)
        ok = (o1.object_ids[m.a] == o2.object_ids[m.b]) & (o1.object_ids[m.a] > 0)
        correct += int(ok.sum())
        total += len(m)
        rel = estimate_relative_pose(o1.boxes, o2.boxes, m)
        if rel is None:
            continue
        verified += 1
        truth = f2.aligned_from_map() @ f1.aligned_from_map().inverse()   # T_2_1
        errors.append((np.degrees(rel.pose.angle_to(truth)), np.linalg.norm(rel.pose.t - truth.t)))
    yaw_err, t_err = np.median(errors, axis=0)
    assert yaw_err < 2.0 and t_err < 0.1, errors          # rgbd preset: 2 deg yaw noise per box
    assert total > 0 and correct / total > 0.8
    assert verified >= 4


def test_pair_evaluation_scores_matches_and_poses():
    from rfm_core.evaluation.matching import evaluate_pairs
    from rfm_core.training.matcher import labelled_pairs, scene_configs
    pairs = labelled_pairs(scene_configs([2100], frames=12), ['ground_truth:perfect', 'ground_truth:rgb'],
                           noise_seeds=(1,), gaps=(2,), min_shared=3, visible=True)
    perfect = evaluate_pairs(pairs['ground_truth:perfect'], ClassicalMatcher())
    assert perfect.pairs == len(pairs['ground_truth:perfect']) >= 4 and perfect.verified == 1.0   # every pair scored
    assert perfect.median_yaw_deg < 0.01 and perfect.median_translation_m < 0.001
    assert perfect.match_precision > 0.8 and perfect.match_recall > 0.8
    noisy = evaluate_pairs(pairs['ground_truth:rgb'], ClassicalMatcher())
    assert noisy.pairs == perfect.pairs
    assert noisy.median_translation_m > perfect.median_translation_m


def test_a_measured_yaw_rules_out_hypotheses_and_one_object_proposes():
    """With the gyroscope's yaw, hypotheses away from it are not considered (a pose the boxes
    alone would give is refused when the measurement says otherwise), and the pose found
    under it agrees with the truth."""
    from rfm_core.matching.relative_pose import YawPrior
    rng = np.random.default_rng(3)
    a = np.array([[2.0, 0.5, 0.4, 1.2, 0.5, 0.8, 0.0], [3.0, -1.0, 0.3, 0.8, 0.3, 0.6, 0.3],
                  [2.5, 1.5, 0.5, 0.6, 1.4, 1.0, -0.2]])
    truth = Pose4(np.radians(12.0), (0.3, -0.2, 0.0))
    b = truth.transform_boxes(a)
    b[:, :3] += rng.normal(0, 0.01, (3, 3))
    m = ObjectMatches(np.arange(3), np.arange(3), np.ones(3))
    free = estimate_relative_pose(a, b, m)
    right = estimate_relative_pose(a, b, m, yaw_prior=YawPrior(truth.yaw, np.radians(3.0)))
    wrong = estimate_relative_pose(a, b, m, yaw_prior=YawPrior(truth.yaw + np.radians(40.0), np.radians(3.0)))
    assert free is not None and right is not None and wrong is None
    assert np.degrees(right.pose.angle_to(truth)) < 1.0 and np.linalg.norm(right.pose.t - truth.t) < 0.05
    # the minimum: two matched objects, both verified under the measured yaw
    two = ObjectMatches(np.arange(2), np.arange(2), np.ones(2))
    single = estimate_relative_pose(a, b, two, yaw_prior=YawPrior(truth.yaw, np.radians(3.0)))
    assert single is not None and len(single.inliers) == 2


def _partial(boxes, shift):
    """Partial boxes of a depth detector: each centre shifted towards the camera (at the
    origin) by its own amount, the orientation kept."""
    out = boxes.copy()
    d = boxes[:, :3] / np.linalg.norm(boxes[:, :3], axis=1, keepdims=True)
    out[:, :3] -= d * np.asarray(shift)[:, None]
    return out


def test_the_refit_takes_its_yaw_from_the_box_faces_not_from_biased_centres():
    """Two views from opposite sides of three objects: each camera's partial boxes sit
    closer to it than the objects (by 4-25 cm, different per object), their orientation
    right. The centres' spread turns a fit on the centres (here by half a degree); the refit
    takes its yaw from the faces' orientations, which do not."""
    objects = np.array([[0.0, -0.8, 0.0, 0.8, 0.5, 0.7, 0.3], [0.3, 0.1, 0.0, 0.6, 0.6, 0.9, -0.2],
                        [-0.2, 1.0, 0.0, 1.0, 0.4, 0.8, 0.9]])
    cam_a = Pose4.from_centre(0.0, (-2.5, 0.0, 0.0))               # T_a_world
    cam_b = Pose4.from_centre(np.pi, (2.5, 0.0, 0.0))              # T_b_world: the other side
    a = _partial(cam_a.transform_boxes(objects), [0.05, 0.25, 0.12])
    b = _partial(cam_b.transform_boxes(objects), [0.22, 0.04, 0.15])
    truth = cam_b @ cam_a.inverse()                                 # T_b_a
    matches = ObjectMatches(np.arange(3), np.arange(3), np.ones(3))
    rel = estimate_relative_pose(a, b, matches, MatchingConfig())
    assert rel is not None and len(rel.inliers) == 3
    centres = kabsch_4dof(a[:, :3], b[:, :3])
    errors = {'centres': np.degrees(centres.angle_to(truth)), 'faces': np.degrees(rel.pose.angle_to(truth))}
    assert errors['centres'] > 0.3 and errors['faces'] < 0.01, errors


def test_camera_heights_replace_the_vertical_translation_where_they_agree():
    """Frames that both measured their height above the floor take the edge's height from it;
    an implausible height (another surface taken for the floor) or a missing one leaves the
    boxes' estimate."""
    from dataclasses import replace as dc_replace  # noqa: PLC0415

    from rfm_core.matching.relative_pose import with_camera_heights  # noqa: PLC0415
    from rfm_core.observations import CameraIntrinsics, FrameObservations  # noqa: PLC0415

    rng = np.random.default_rng(3)
    a = scene_boxes(rng, 6)
    truth = Pose4(0.4, (1.0, -0.5, 0.08))               # T_b_a: frame a's camera 8 cm higher
    b = truth.transform_boxes(a)
    b[:, 2] += rng.normal(0.0, 0.03, len(b))          # box centres' heights are noisy
    idx = np.arange(len(a))
    rel = estimate_relative_pose(a, b, ObjectMatches(idx, idx, np.ones(len(a))))
    assert rel is not None
    assert abs(rel.pose.t[2] - 0.08) > 0.002              # the boxes alone miss the height a little
    intr = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)
    source = FrameObservations(0, 'c', intr, [0, 0, -1], camera_height=1.50)     # frame b
    target = FrameObservations(1, 'c', intr, [0, 0, -1], camera_height=1.58)     # frame a
    fixed = with_camera_heights(dc_replace(rel), source, target)
    assert fixed.pose.t[2] == pytest.approx(0.08, abs=1e-9)
    np.testing.assert_allclose(fixed.pose.t[:2], rel.pose.t[:2])
    assert fixed.pose.yaw == rel.pose.yaw
    # a table top taken for the floor in one frame: 0.7 m off the boxes, which then decide
    table = FrameObservations(1, 'c', intr, [0, 0, -1], camera_height=0.88)
    assert with_camera_heights(dc_replace(rel), source, table).pose.t[2] == rel.pose.t[2]
    unknown = FrameObservations(1, 'c', intr, [0, 0, -1])
    assert np.isnan(unknown.camera_height)
    assert with_camera_heights(dc_replace(rel), source, unknown).pose.t[2] == rel.pose.t[2]
    off = MatchingConfig(height_tolerance_m=0.0)
    assert with_camera_heights(dc_replace(rel), source, target, off).pose.t[2] == rel.pose.t[2]
    # a non-physical height is no measurement
    assert np.isnan(FrameObservations(1, 'c', intr, [0, 0, -1], camera_height=-1.0).camera_height)


def test_walls_correct_the_horizontal_translation_along_their_normals():
    """Walls both frames measured fix the translation along their normals (two at an angle:
    all of it; one: across the wall); a wall the boxes put too far from the other frame's, or
    turned away from it, is no evidence; yaw and height are kept."""
    from dataclasses import replace as dc_replace  # noqa: PLC0415

    from rfm_core.matching.relative_pose import RelativePose, with_walls  # noqa: PLC0415
    from rfm_core.observations import CameraIntrinsics, FrameObservations  # noqa: PLC0415

    intr = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)
    truth = Pose4(np.radians(12.0), (0.35, -0.2, 0.05))                  # T_source_target
    source_walls = np.array([[1.0, 0.0, 2.5], [0.0, -1.0, 1.8]])        # n . p = d, source frame
    c, s_ = np.cos(truth.yaw), np.sin(truth.yaw)
    rot = np.array([[c, -s_], [s_, c]])

    def seen_from_target(walls):                                        # n_t = R^T n_s, d_t = d_s - n_s . t
        return np.c_[walls[:, :2] @ rot, walls[:, 2] - walls[:, :2] @ np.asarray(truth.t)[:2]]

    source = FrameObservations(0, 'c', intr, [0, 0, -1], walls=source_walls)
    target = FrameObservations(1, 'c', intr, [0, 0, -1], walls=seen_from_target(source_walls))
    boxes = RelativePose(Pose4(truth.yaw, np.asarray(truth.t) + [0.08, -0.06, 0.01]), np.zeros((0, 2), int),
                         np.zeros(0), np.zeros(0), 0.0, 3)              # the boxes' estimate, 10 cm off
    fixed = with_walls(dc_replace(boxes), source, target)
    assert np.linalg.norm(np.asarray(fixed.pose.t)[:2] - np.asarray(truth.t)[:2]) < 0.005
    assert fixed.pose.yaw == boxes.pose.yaw and fixed.pose.t[2] == boxes.pose.t[2]
    one = FrameObservations(1, 'c', intr, [0, 0, -1], walls=seen_from_target(source_walls)[:1])
    t = with_walls(dc_replace(boxes), source, one).pose.t                # the x-normal wall only
    assert abs(t[0] - truth.t[0]) < 0.005 and t[1] == pytest.approx(boxes.pose.t[1], abs=0.003)
    far = seen_from_target(source_walls)
    far[:, 2] += 0.5                                                     # another plane, 50 cm away
    assert with_walls(dc_replace(boxes), source, FrameObservations(1, 'c', intr, [0, 0, -1], walls=far)).pose \
        == boxes.pose
    # a yaw 1.5 deg off as well: the walls' normals turn it back, the matched boxes keep their place
    boxes_b = np.array([[1.5, 0.4, 0.0, 0.5, 0.5, 0.5, 0.0], [2.0, -0.6, 0.0, 0.5, 0.5, 0.5, 0.0]])
    target_boxes = FrameObservations(1, 'c', intr, [0, 0, -1], boxes=boxes_b, scores=[1.0, 1.0],
                                     walls=seen_from_target(source_walls))
    skewed = RelativePose(Pose4(truth.yaw + np.radians(1.5), np.asarray(truth.t) + [0.05, 0.03, 0.0]),
                          np.array([[0, 0], [1, 1]]), np.ones(2), np.ones(2), 0.0, 2)
    fixed = with_walls(dc_replace(skewed), source, target_boxes)
    assert abs(np.degrees(wrap_angle(fixed.pose.yaw - truth.yaw))) < 0.1
    assert np.linalg.norm(np.asarray(fixed.pose.t)[:2] - np.asarray(truth.t)[:2]) < 0.01
    turned = FrameObservations(1, 'c', intr, [0, 0, -1], walls=[[0.6, 0.8, 2.0]])
    assert with_walls(dc_replace(boxes), source, turned).pose == boxes.pose
    off = MatchingConfig(wall_tolerance_m=0.0)
    assert with_walls(dc_replace(boxes), source, target, off).pose == boxes.pose
    for bad in ([[1.0, 0.0]], [[0.0, 0.0, 2.0]], [[1.0, 0.0, -1.0]], [[1.0, 0.0, np.nan]]):
        with pytest.raises(ValueError, match='walls'):
            FrameObservations(1, 'c', intr, [0, 0, -1], walls=bad)




def _separate_views(world_boxes: np.ndarray, t_a_world: Pose4, t_b_world: Pose4):
    """Two views' FrameObservations of ``world_boxes`` (gravity-aligned frames), full and fitted
    boxes alike, no embeddings."""
    from rfm_core.observations import CameraIntrinsics, FrameObservations  # noqa: PLC0415

    intr = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)

    def view(pose, stamp):
        boxes = pose.transform_boxes(world_boxes)
        return FrameObservations(stamp, 'camera', intr, np.array([0.0, 1.0, 0.0]), boxes, np.ones(len(boxes)),
                                 full_boxes=boxes.copy())
    return view(t_a_world, 1), view(t_b_world, 2)


def test_separate_views_are_related_by_the_layout_of_their_boxes_and_an_ambiguous_one_is_not():
    """A matcher that matches nothing (photos far apart): the full boxes' layout alone gives the
    relative pose; a layout that looks the same from two poses (a square of like boxes) gives
    none, and neither do two views of different rooms."""
    from rfm_core.matching.relative_pose import estimate_by_consensus  # noqa: PLC0415

    world = np.array([[1.0, 2.0, 0.40, 0.8, 0.5, 0.8, 0.1], [2.6, 2.3, 0.45, 1.6, 0.9, 0.9, 0.3],
                      [1.8, 3.9, 0.90, 0.4, 0.4, 1.8, 0.0], [3.9, 1.1, 0.25, 0.6, 0.6, 0.5, 1.2],
                      [0.2, 0.8, 0.35, 1.2, 0.4, 0.7, -0.4]])
    t_a, t_b = Pose4(0.4, (-1.0, -0.5, -1.4)), Pose4(2.3, (1.5, -3.0, -1.4))
    a, b = _separate_views(world, t_a, t_b)
    rel = estimate_by_consensus(a, b)                                    # T_b_a
    truth = t_b @ t_a.inverse()
    assert rel is not None and len(rel.inliers) == 5
    assert (truth.inverse() @ rel.pose).within(0.02, 0.5)
    square = np.array([[x, y, 0.4, 0.5, 0.5, 0.8, 0.0] for x, y in ((0, 0), (2, 0), (2, 2), (0, 2))])
    assert estimate_by_consensus(*_separate_views(square, t_a, t_b)) is None
    other = world.copy()
    other[:, :2] = np.random.default_rng(0).uniform(0, 5, (5, 2))          # the same furniture, elsewhere
    a2, _ = _separate_views(other, t_a, t_b)
    found = estimate_by_consensus(a2, b)
    assert found is None or len(found.inliers) < 3
