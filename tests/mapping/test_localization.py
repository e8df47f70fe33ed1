"""Localization mode as a stream (rfm_core.mapping.localization): a track, confirmation by a
later frame, kidnapping; the whole-map check's floor of three explained detections; the floor
and walls in relocalized poses; the classical matcher where the learned one places nothing;
depth points: a frame of a track, a frame no keyframe saw all of, the frames before a new
track, a view no keyframe places (from the map's objects)."""
import copy
from dataclasses import replace

import numpy as np
import pytest

from rfm_core.evaluation.pipeline import run_capture
from rfm_core.geometry import Pose4, wrap_angle, yaw_matrix
from rfm_core.mapping.localization import StreamLocalizer, motion_prior, on_points
from rfm_core.mapping.map_io import load_map, save_map
from rfm_core.mapping.mapper import Mapper, MapperConfig
from rfm_core.mapping.relocalization import MotionPrior
from rfm_core.matching.classical import ObjectMatches
from rfm_core.observations import FrameObservations
from rfm_core.session import MapSession
from rfm_core.sim.capture import CaptureConfig

SCENE = CaptureConfig(seed=40, frames=50, fps=5)
STEP_NS = 500_000_000                      # the queries come at 2 Hz


@pytest.fixture(scope='module')
def saved(tmp_path_factory):
    """A saved map of one walk."""
    return save_map(run_capture(SCENE, 'ground_truth:rgbd', noise_seed=3).mapper,
                    tmp_path_factory.mktemp('map') / 'room.rfm')


@pytest.fixture(scope='module')
def room(saved):
    """The map, loaded fresh in localization mode."""
    mapper = Mapper()
    load_map(mapper, saved)
    mapper.mode = 'localization'
    return mapper


def _views(mapper):
    """The map's registered keyframes' own views (four or more detections), in walking order,
    stamped again 0.5 s apart, with their T_view_map."""
    ids = [k for k in sorted(mapper.poses) if len(mapper.keyframes[k]) >= 4]
    return [(replace(mapper.keyframes[k], stamp_ns=(i + 1) * STEP_NS), mapper.poses[k]) for i, k in enumerate(ids)]


def _stream(mapper, **changes):
    """A stream against ``mapper``'s map (shared, not copied) with relocalization settings changed."""
    changed = copy.copy(mapper)
    changed.config = replace(mapper.config, relocalization=replace(mapper.config.relocalization, **changes))
    return StreamLocalizer(changed)


def _close(a, b, metres=0.1, degrees=3.0):
    d = a.inverse() @ b
    return np.linalg.norm(d.t) < metres and abs(np.degrees(d.yaw)) < degrees


def test_the_first_pose_waits_for_a_second_frame_then_the_track_places_every_frame(room):
    views = _views(room)
    assert len(views) >= 5
    stream = _stream(room)
    why = []
    assert stream.step(views[0][0], why) == [] and 'waits for a later frame' in why[-1]
    both = stream.step(views[1][0])
    assert [o.stamp_ns for o, _ in both] == [views[0][0].stamp_ns, views[1][0].stamp_ns]     # the held one first
    for (obs, truth), (_, reloc) in zip(views[:2], both):
        assert _close(reloc.pose, truth)
    # consecutive keyframes are close in space: the track places each of the rest
    for obs, truth in views[2:]:
        placed = stream.step(obs)
        if np.linalg.norm(truth.inverse().t - stream.track[-1][1].inverse().t) < 1.0:
            assert len(placed) == 1 and _close(placed[0][1].pose, truth)
    assert stream.counts['confirmed'] == 1 and stream.counts['tracked'] >= 1


def test_a_pose_that_contradicts_the_track_is_held_and_two_that_agree_replace_it(room):
    """A frame whose pose lies further from the track's last than the camera can move in
    0.5 s is not published (a look-alike in a real room); two such frames that agree with each
    other are a kidnapped camera, and replace the track."""
    views = _views(room)
    centres = np.array([p.inverse().t for _, p in views])
    far = int(np.argmax(np.linalg.norm(centres - centres[0], axis=1)))
    assert np.linalg.norm(centres[far] - centres[0]) > 2.0
    stream = _stream(room)
    first, second = views[0][0], replace(views[0][0], stamp_ns=views[0][0].stamp_ns + STEP_NS)
    assert stream.step(first) == [] and len(stream.step(second)) == 2
    jump = replace(views[far][0], stamp_ns=second.stamp_ns + STEP_NS, imu_rotation=None, imu_epoch=0)
    why = []
    assert stream.step(jump, why) == [] and 'contradicts the track' in why[-1]
    # alone, the service's way, the same frame is placed where its keyframe is
    assert _close(room.relocalize(jump).pose, views[far][1])
    again = replace(jump, stamp_ns=jump.stamp_ns + STEP_NS)
    moved = stream.step(again)
    assert [o.stamp_ns for o, _ in moved] == [jump.stamp_ns, again.stamp_ns]
    assert _close(moved[-1][1].pose, views[far][1]) and stream.counts['confirmed'] == 2


def test_a_held_pose_expires_and_a_track_ends_after_the_gap(room):
    views = _views(room)
    stream = _stream(room, stream_max_gap_s=1.0)
    assert stream.step(views[0][0]) == []
    late = replace(views[1][0], stamp_ns=views[0][0].stamp_ns + 3 * STEP_NS)    # 1.5 s later
    assert stream.step(late) == [] and len(stream.held) == 1                    # the first expired
    assert len(stream.step(replace(views[1][0], stamp_ns=late.stamp_ns + STEP_NS))) == 2


def test_two_detections_verify_nothing_alone_but_do_where_the_track_predicts_them(room):
    """A pose built from two objects that explains only those two is refused against the
    whole map (min_explained: all of a small query, but at least three); where a live track
    predicts the camera (the gyroscope's yaw, walking reach), two suffice."""
    k = max(room.poses, key=lambda i: len(room.keyframes[i]))
    view, truth = room.keyframes[k], room.poses[k]
    full = room.relocalize(view)
    assert full is not None and _close(full.pose, truth)
    two = view.subset(sorted(full.inliers[:2, 0].tolist()))
    why = []
    assert room.relocalize(two, why) is None
    assert 'need 3' in why[-1] or 'no candidate keyframe' in why[-1], why
    t = truth.inverse()
    prior = MotionPrior(t.yaw, t.t + np.array([0.2, 0.0, 0.0]), 0.5, np.radians(5.0))
    tracked = room.relocalize(two, None, prior)
    assert tracked is not None and _close(tracked.pose, truth, 0.25, 5.0)     # not wrong (two objects: coarse)
    # ... and a prediction somewhere else admits no pose
    assert room.relocalize(two, None, MotionPrior(t.yaw, t.t + np.array([3.0, 0.0, 0.0]), 0.5,
                                                 np.radians(5.0))) is None


def test_a_loaded_map_keeps_the_sessions_way_of_localizing(saved):
    """A map file carries the settings that built it, and the session takes them, except
    how localization mode localizes (relocalization.stream*: not what built the map)."""
    from rfm_core.mapping.frame_log import camera_to_map
    from rfm_core.mapping.mapper import MapperConfig
    from rfm_core.session import MapSession
    config = MapperConfig()
    mine = replace(config, relocalization=replace(config.relocalization, stream_max_gap_s=5.0, min_explained=5))
    session = MapSession(mine)
    _, changed = session.load(saved)
    assert session.mapper.config.relocalization.min_explained == 4 and 'relocalization.min_explained' in changed
    assert session.mapper.config.relocalization.stream_max_gap_s == 5.0
    assert 'relocalization.stream_max_gap_s' not in changed
    session.mode = 'localization'
    view, truth = _views(session.mapper)[0]
    assert session.localize(view) == []               # held until a later frame agrees
    placed = session.localize(replace(view, stamp_ns=view.stamp_ns + STEP_NS))
    assert [p.stamp_ns for p in placed] == [view.stamp_ns, view.stamp_ns + STEP_NS]
    expected = camera_to_map(truth, view.gravity_cam)
    assert np.linalg.norm(placed[0].matrix[:3, 3] - expected[:3, 3]) < 0.1


def test_walls_and_the_floor_a_query_shares_with_the_map_correct_its_pose(saved):
    """Boxes a depth detector saw in part (cut by the image border, hidden behind others)
    move their centres, and a relocalized pose with them; the walls and the floor the query
    and a keyframe both measured fix its yaw, its height and its translation across the
    walls, as they fix the view graph's edges. Here every box of a keyframe's own view is
    6-7 cm off: its pose is put as far off by the boxes alone, and within a centimetre with
    the two walls of the room and the floor."""
    mapper = Mapper()
    load_map(mapper, saved)
    mapper.mode = 'localization'
    centres = np.array([p.inverse().t for p in mapper.poses.values()])
    # two walls at right angles, each 1.5 m beyond the keyframes: n . p = d in the map frame (n away from them)
    walls_map = np.array([[1.0, 0.0, centres[:, 0].max() + 1.5], [0.0, -1.0, 1.5 - centres[:, 1].min()]])
    floor_z = -1.4
    for k, pose in mapper.poses.items():                               # T_kf_map: n_kf = R n, d_kf = d + n_kf . t
        normals = walls_map[:, :2] @ yaw_matrix(pose.yaw)[:2, :2].T
        mapper.keyframes[k] = replace(mapper.keyframes[k], walls=np.c_[normals, walls_map[:, 2] + normals @ pose.t[:2]],
                                      camera_height=-pose.t[2] - floor_z)
    k = max(mapper.poses, key=lambda i: len(mapper.keyframes[i]))
    view = mapper.keyframes[k]
    shift = np.array([0.06, -0.05, 0.03])
    query = replace(view, boxes=view.boxes + np.r_[shift, np.zeros(4)],
                    full_boxes=None if view.full_boxes is None else view.full_boxes + np.r_[shift, np.zeros(4)])
    truth = mapper.poses[k]
    off = mapper.relocalize(replace(query, walls=np.zeros((0, 3)), camera_height=float('nan')))    # boxes only
    assert off is not None and np.linalg.norm((off.pose.inverse() @ truth).t) > 0.04
    fixed = mapper.relocalize(query)
    assert fixed is not None
    assert np.linalg.norm((fixed.pose.inverse() @ truth).t) < 0.01
    assert abs(np.degrees(wrap_angle(fixed.pose.yaw - truth.yaw))) < 0.1


class _MatchesNothing:
    """A relocalization matcher that proposes no match for any pair (as the learned matcher,
    trained on pairs of one walk, often does between two walks)."""

    def match_many(self, a, others):
        return [ObjectMatches(np.zeros(0, int), np.zeros(0, int), np.zeros(0)) for _ in others]


def test_keyframes_the_learned_matcher_does_not_place_are_matched_again_by_the_classical_one(saved):
    """A candidate keyframe the (learned) matcher verifies no pose with is matched again by
    the classical matcher, whose proposals the relative-pose test and the whole-map check
    sort out: a keyframe's own view, which that matcher cannot match, relocalizes at the
    keyframe's pose; a view neither matches (its embeddings turned around) is refused with
    the reason."""
    mapper = Mapper(matcher=_MatchesNothing())
    load_map(mapper, saved)
    mapper.mode = 'localization'
    k = max(mapper.poses, key=lambda i: len(mapper.keyframes[i]))
    found = mapper.relocalize(mapper.keyframes[k])
    assert found is not None and _close(found.pose, mapper.poses[k], metres=0.05, degrees=1.0)
    why = []
    view = mapper.keyframes[k]
    assert mapper.relocalize(replace(view, embeddings=-view.embeddings), why) is None
    assert why and 'no candidate keyframe' in why[0]


def _room_points(centres: np.ndarray, spacing: float = 0.15) -> np.ndarray:
    """A room around the keyframes' camera centres (map frame): floor, four walls, two boxes."""
    lo, hi = centres[:, :2].min(0) - 1.5, centres[:, :2].max(0) + 1.5
    floor_z = centres[:, 2].min() - 1.3
    x, y = np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing)
    z = np.arange(floor_z, floor_z + 2.5, spacing)
    parts = [np.c_[np.stack(np.meshgrid(x, y), -1).reshape(-1, 2), np.full(len(x) * len(y), floor_z)]]
    for wall_x in (lo[0], hi[0]):
        parts.append(np.c_[np.full(len(y) * len(z), wall_x), np.stack(np.meshgrid(y, z), -1).reshape(-1, 2)])
    for wall_y in (lo[1], hi[1]):
        xz = np.stack(np.meshgrid(x, z), -1).reshape(-1, 2)
        parts.append(np.c_[xz[:, 0], np.full(len(xz), wall_y), xz[:, 1]])
    for cx, cy in ((lo[0] + 1.0, lo[1] + 1.0), (hi[0] - 1.0, lo[1] + 1.2)):
        s = np.arange(-0.3, 0.3, spacing / 2)
        u, v = (a.ravel() for a in np.meshgrid(s, s))
        parts += [np.c_[cx + 0.3 + 0 * u, cy + u, floor_z + 0.3 + v],
                  np.c_[cx + u, cy + v, np.full(len(u), floor_z + 0.6)]]
    return np.concatenate(parts)


def _room_map(saved):
    """The saved map in localization mode, each keyframe seeing the room's points
    (:func:`_room_points`), and those points."""
    mapper = Mapper()
    load_map(mapper, saved)
    mapper.mode = 'localization'
    room = _room_points(np.array([p.inverse().t for p in mapper.poses.values()]))
    for k, pose in mapper.poses.items():
        mapper.keyframes[k] = replace(mapper.keyframes[k], cloud=pose.transform_points(room).astype(np.float32))
    return mapper, room


def _points_of(room, t_view_map: Pose4, like: FrameObservations, stamp_ns: int, seed: int = 0):
    """A frame at ``t_view_map`` that sees the room's points and nothing else."""
    rng = np.random.default_rng(seed)
    cloud = t_view_map.transform_points(room) + rng.normal(0, 0.005, room.shape)
    return FrameObservations(stamp_ns, like.frame_id, like.intrinsics, like.gravity_cam,
                             cloud=cloud[rng.permutation(len(cloud))[:4000]].astype(np.float32))


def test_a_pose_lifted_by_a_seat_taken_for_the_floor_is_put_back_on_the_maps_floor(saved):
    """A keyframe that took a seat for the floor, and partial boxes cut at it, lift a
    relocalized pose by the seat's height; the map's floor (what most keyframes around agree
    on) and its merged depth points put it back: the query's pose is aligned on the map's
    points from the height its own floor gives it, and kept for putting more of its points on
    the map's surfaces. Without the query's floor the lifted pose stays."""
    from rfm_core.mapping.relocalization import on_map_points  # noqa: PLC0415
    mapper = Mapper()
    load_map(mapper, saved)
    mapper.mode = 'localization'
    centres = np.array([p.inverse().t for p in mapper.poses.values()])
    room = _room_points(centres)
    floor_z, seat = centres[:, 2].min() - 1.3, 0.35
    for i, k in enumerate(sorted(mapper.poses)):        # every keyframe measured the floor; one in 8 a seat
        pose = mapper.poses[k]
        mapper.keyframes[k] = replace(mapper.keyframes[k], cloud=pose.transform_points(room).astype(np.float32),
                                      camera_height=pose.inverse().t[2] - floor_z - (seat if i % 8 == 3 else 0.0))
    index = mapper.map_index()
    assert index.floor_under(centres[0]) == pytest.approx(floor_z, abs=1e-6)
    k = max(mapper.poses, key=lambda i: len(mapper.keyframes[i]))
    truth = mapper.poses[k]                                                          # T_view_map
    rng = np.random.default_rng(2)
    cloud = truth.transform_points(room) + rng.normal(0, 0.005, room.shape)
    query = replace(mapper.keyframes[k], cloud=cloud[rng.permutation(len(cloud))[:4000]].astype(np.float32),
                    camera_height=truth.inverse().t[2] - floor_z)
    lifted = (Pose4(0.0, (0.0, 0.0, seat)) @ truth.inverse()).inverse()              # 35 cm up
    placed = on_map_points(query, lifted, index, mapper.config.matching, 2)
    assert _close(placed, truth, metres=0.02, degrees=0.3)
    kept = on_map_points(replace(query, camera_height=float('nan')), lifted, index, mapper.config.matching, 2)
    assert not _close(kept, truth, metres=0.1, degrees=3.0)


def test_a_frame_with_depth_points_only_is_placed_on_the_maps_surfaces(saved):
    """A frame of a live track without detections (the detector was behind and sent its
    depth points only) is aligned to the nearest map keyframe's points from the predicted
    pose and accepted: within a centimetre of where it is. Without its points, it is not placed."""
    mapper, room = _room_map(saved)
    views = _views(mapper)
    rng = np.random.default_rng(0)
    last, last_pose = views[1]
    seen = last_pose.inverse()                                         # T_map_view, moved on a little
    truth = Pose4(seen.yaw + np.radians(2.0), seen.t + np.array([0.12, -0.08, 0.01])).inverse()
    cloud = truth.transform_points(room) + rng.normal(0, 0.005, room.shape)
    query = FrameObservations(last.stamp_ns + STEP_NS, last.frame_id, last.intrinsics, last.gravity_cam,
                              cloud=cloud[rng.permutation(len(cloud))[:4000]].astype(np.float32))
    for with_points in (True, False):
        stream = StreamLocalizer(mapper)
        for view, _ in views[:2]:                                      # the track: the second confirms the first
            stream.step(view)
        assert len(stream.track) == 2
        placed = stream.step(query if with_points else replace(query, cloud=query.cloud[:0]))
        if not with_points:
            assert placed == [] and stream.counts['points'] == 0
            continue
        assert len(placed) == 1 and placed[0][1].num_inliers == 0 and stream.counts['points'] == 1
        assert _close(placed[0][1].pose, truth, metres=0.01, degrees=0.2)


def test_a_track_on_the_points_starts_each_alignment_where_the_cameras_velocity_puts_it(saved):
    """Frames 0.5 s apart that only the depth points place: a camera walking at 0.7 m/s is
    0.35 m from the last frame, beyond the reach of an alignment started there (its first
    correspondences are searched within 0.25 m). The track's velocity predicts where it is,
    and each alignment starts there: every frame is placed within a centimetre."""
    mapper, room = _room_map(saved)
    views = _views(mapper)
    start = views[1][1].inverse()                                      # T_map_view of a confirmed frame
    step = yaw_matrix(start.yaw) @ np.array([0.0, 0.35, 0.0])          # sideways, 0.35 m per frame
    stream = StreamLocalizer(mapper)
    for view, _ in views[:2]:                                          # the track: the second confirms the first
        stream.step(view)
    stream.track = [(views[0][0], Pose4(start.yaw, start.t - step).inverse()), (views[1][0], start.inverse())]
    for i in range(1, 4):
        truth = Pose4(start.yaw, start.t + i * step).inverse()
        placed = stream.step(_points_of(room, truth, views[1][0], views[1][0].stamp_ns + i * STEP_NS, seed=i))
        assert len(placed) == 1 and _close(placed[0][1].pose, truth, metres=0.01, degrees=0.2), i


def test_the_objects_overrule_a_track_that_the_points_alone_would_carry_on(saved):
    """A frame of a live track whose depth points lie on the map's surfaces near where the
    track predicts it, but whose objects place it unambiguously elsewhere: the points alone
    are not trusted (a track slides on them), the frame is held as one that contradicts the
    track, and a second frame like it replaces the track where the objects put it."""
    mapper, room = _room_map(saved)
    views = _views(mapper)
    centres = np.array([p.inverse().t for _, p in views])
    far = int(np.argmax(np.linalg.norm(centres - centres[1], axis=1)))
    assert np.linalg.norm(centres[far] - centres[1]) > 2.0
    stream = StreamLocalizer(mapper)
    for view, _ in views[:2]:
        stream.step(view)
    assert len(stream.track) == 2
    near = views[1][1]                                                 # where the track is
    stamp = views[1][0].stamp_ns + STEP_NS
    frame = replace(views[far][0], stamp_ns=stamp, imu_rotation=None, imu_epoch=0,
                    cloud=_points_of(room, near, views[1][0], stamp).cloud)
    assert on_points(frame, motion_prior(stream.track, frame, mapper.config.relocalization), mapper.map_index(),
                     mapper.config.matching) is not None               # the points alone place it near the track
    why = []
    assert stream.step(frame, why) == [] and 'contradicts the track' in why[-1]
    assert stream.counts['points'] == 0
    again = replace(frame, stamp_ns=stamp + STEP_NS)
    moved = stream.step(again)
    assert [o.stamp_ns for o, _ in moved] == [stamp, again.stamp_ns]
    assert _close(moved[-1][1].pose, views[far][1])


def test_a_frame_the_points_alone_place_does_not_end_the_poses_held_against_the_track(saved):
    """A frame whose objects contradict the track is held; the next frame has depth points
    only, which carry the track on (and place the held frame on it, walking back). It
    confirms nothing: the held pose stays held, and a third frame whose objects agree with it
    replaces the track where the objects put both, the held frame placed again."""
    mapper, room = _room_map(saved)
    views = _views(mapper)
    centres = np.array([p.inverse().t for _, p in views])
    far = int(np.argmax(np.linalg.norm(centres - centres[1], axis=1)))
    stream = StreamLocalizer(mapper)
    for view, _ in views[:2]:
        stream.step(view)
    near, stamp = views[1][1], views[1][0].stamp_ns + STEP_NS
    frame = replace(views[far][0], stamp_ns=stamp, imu_rotation=None, imu_epoch=0,
                    cloud=_points_of(room, near, views[1][0], stamp).cloud)
    assert stream.step(frame) == [] and len(stream.held) == 1
    points_only = _points_of(room, near, views[1][0], stamp + STEP_NS, seed=1)
    carried = stream.step(points_only)
    assert [o.stamp_ns for o, _ in carried] == [stamp, points_only.stamp_ns] and len(stream.held) == 1
    again = replace(frame, stamp_ns=stamp + 2 * STEP_NS)
    moved = stream.step(again)
    assert [o.stamp_ns for o, _ in moved] == [stamp, again.stamp_ns]
    assert _close(moved[0][1].pose, views[far][1]) and _close(moved[-1][1].pose, views[far][1])


def test_a_frame_no_keyframe_saw_all_of_is_placed_on_the_maps_merged_points(saved):
    """Each keyframe saw one slice of the room (by bearing from its centre); the query sees
    all of it. No single keyframe's points place it (too little of the view lies on them),
    the map's points, every keyframe's merged, do: within a centimetre of where it is."""
    from rfm_core.matching.relative_pose import track_on_points  # noqa: PLC0415
    mapper = Mapper()
    load_map(mapper, saved)
    mapper.mode = 'localization'
    centres = np.array([p.inverse().t for p in mapper.poses.values()])
    room = _room_points(centres)
    middle = room[:, :2].mean(0)
    bearing = np.arctan2(room[:, 1] - middle[1], room[:, 0] - middle[0])
    ids = sorted(mapper.poses)
    slices = np.floor((bearing + np.pi) / (2 * np.pi) * len(ids)).astype(int) % len(ids)
    for i, k in enumerate(ids):
        part = room[slices == i]
        mapper.keyframes[k] = replace(mapper.keyframes[k],
                                      cloud=mapper.poses[k].transform_points(part).astype(np.float32))
    views = _views(mapper)
    rng = np.random.default_rng(1)
    last, last_pose = views[1]
    seen = last_pose.inverse()
    truth = Pose4(seen.yaw - np.radians(2.0), seen.t + np.array([-0.1, 0.1, 0.0])).inverse()
    cloud = truth.transform_points(room) + rng.normal(0, 0.005, room.shape)
    query = FrameObservations(last.stamp_ns + STEP_NS, last.frame_id, last.intrinsics, last.gravity_cam,
                              cloud=cloud[rng.permutation(len(cloud))[:4000]].astype(np.float32))
    predicted = seen                                                   # T_map_view where the track left it
    for k in ids:                                                      # no keyframe alone places it
        found = track_on_points(mapper.poses[k] @ predicted, mapper.keyframes[k], query, mapper.config.matching)
        assert found is None or found.free or not _close(found.pose.inverse() @ mapper.poses[k], truth, 0.01, 0.2)
    stream = StreamLocalizer(mapper)
    for view, _ in views[:2]:
        stream.step(view)
    assert len(stream.track) == 2
    placed = stream.step(query)
    assert len(placed) == 1 and stream.counts['points'] == 1
    assert _close(placed[0][1].pose, truth, metres=0.01, degrees=0.2)


def test_a_new_track_walks_back_over_the_frames_nothing_placed_before_it(saved):
    """A frame before the first pose of a track (depth points only: nothing places it on
    its own) is placed once the track is confirmed, walking back from its first frame: late,
    before the track's frames, within a centimetre of where it is."""
    mapper, room = _room_map(saved)
    views = _views(mapper)
    first, first_pose = views[0]
    seen = first_pose.inverse()
    truth = Pose4(seen.yaw + np.radians(1.5), seen.t + np.array([0.1, 0.05, 0.0])).inverse()
    rng = np.random.default_rng(2)
    cloud = truth.transform_points(room) + rng.normal(0, 0.005, room.shape)
    early = FrameObservations(first.stamp_ns - STEP_NS // 2, first.frame_id, first.intrinsics, first.gravity_cam,
                              cloud=cloud[rng.permutation(len(cloud))[:4000]].astype(np.float32))
    stream = StreamLocalizer(mapper)
    assert stream.step(early) == [] and stream.step(first) == []          # no track yet: waits
    placed = stream.step(views[1][0])                                      # confirms the first view
    assert [o.stamp_ns for o, _ in placed] == [early.stamp_ns, first.stamp_ns, views[1][0].stamp_ns]
    assert stream.counts['walked_back'] == 1 and stream.unplaced == []
    assert _close(placed[0][1].pose, truth, metres=0.01, degrees=0.2)


def test_a_view_no_keyframe_places_is_placed_by_the_maps_objects_and_depth_points(saved):
    """A view a little away from a keyframe's, whose detections no keyframe verifies (no
    matcher proposes a match): a box correspondence with the map's objects brings it near,
    the map's depth points place it, within a centimetre of where it is (no object inliers).
    Without depth points it is refused: no keyframe verified it."""
    session = MapSession(MapperConfig(), matcher=_MatchesNothing())      # as the mapper node's rfm/relocalize
    session.load(saved)
    mapper = session.mapper
    room = _room_points(np.array([p.inverse().t for p in mapper.poses.values()]))
    for k, pose in mapper.poses.items():
        mapper.keyframes[k] = replace(mapper.keyframes[k], cloud=pose.transform_points(room).astype(np.float32))
    k = max(mapper.poses, key=lambda i: len(mapper.keyframes[i]))
    kf = mapper.keyframes[k]
    step = Pose4(np.radians(3.0), (0.15, -0.1, 0.0))                     # T_view_k
    truth = step @ mapper.poses[k]                                       # T_view_map
    rng = np.random.default_rng(3)
    cloud = truth.transform_points(room) + rng.normal(0, 0.005, room.shape)
    view = replace(kf, stamp_ns=kf.stamp_ns + STEP_NS, boxes=step.transform_boxes(kf.boxes),
                   embeddings=-kf.embeddings,                           # nor does the classical matcher
                   full_boxes=None if kf.full_boxes is None else step.transform_boxes(kf.full_boxes),
                   walls=np.zeros((0, 3)), camera_height=float('nan'),
                   cloud=cloud[rng.permutation(len(cloud))[:4000]].astype(np.float32))
    found, message = session.relocalize(view)
    assert found is not None and found.num_inliers == 0 and found.explained >= min(4, len(view)), message
    assert _close(found.pose, truth, metres=0.01, degrees=0.2)
    assert "on the map's depth points" in message
    why = []
    assert mapper.relocalize(replace(view, cloud=np.zeros((0, 3), np.float32)), why) is None
    assert 'no candidate keyframe' in why[0]
