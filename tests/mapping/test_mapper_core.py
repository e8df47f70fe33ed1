"""The mapper node's policy without ROS (rfm_core.mapper_core): the files a request may name,
autosave, the object map's throttle, and what one tick returns."""
import os

import numpy as np
import pytest
from sim_frames import detected_frames

from rfm_core.config import MapperNodeConfig
from rfm_core.mapper_core import Autosave, MapFiles, MapperCore, Throttle, default_map_path
from rfm_core.mapping.map_io import read_map
from rfm_core.matching.view_graph import ViewGraphBuilder
from rfm_core.observations import EdgeRecord
from rfm_core.settings import with_values


@pytest.fixture(scope='module')
def observations():
    return detected_frames(frames=40)


class _Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_requests_name_files_inside_map_dir_only(tmp_path):
    files = MapFiles(str(tmp_path / 'maps' / 'map.rfm'))
    assert files.dir == (tmp_path / 'maps').resolve()
    assert files.resolve('') == str(tmp_path / 'maps' / 'map.rfm')
    assert files.resolve('other.rfm') == str((tmp_path / 'maps' / 'other.rfm').resolve())
    assert files.resolve(str(tmp_path / 'maps' / 'sub' / 'a.rfm')).endswith('sub/a.rfm')
    (tmp_path / 'maps').mkdir()
    os.symlink(tmp_path, tmp_path / 'maps' / 'out')                 # a link leading outside
    for bad in ('../elsewhere.rfm', str(tmp_path / 'elsewhere.rfm'), 'out/elsewhere.rfm', 'a\x00b', 'x' * 2000):
        with pytest.raises(ValueError):
            files.resolve(bad)
    assert MapFiles('', str(tmp_path)).path == default_map_path()
    assert default_map_path({'ROS_HOME': '/r'}) == '/r/rfm/map.rfm'


def test_autosave_every_n_keyframes_then_by_growth():
    autosave = Autosave(every_n=10, growth=0.1)
    assert not autosave.due(9, 9) and autosave.due(10, 10)
    assert not autosave.due(40, 500) and autosave.due(50, 500)      # a large map: 10% of it
    assert not Autosave(every_n=0, growth=0.1).due(1000, 1000)
    # a map that stopped growing: its frames after a while, never with none to save
    timed = Autosave(every_n=10, growth=0.1, period_s=60.0)
    assert timed.due(0, 30, unsaved_frames=5, waited_s=60.0) and not timed.due(0, 30, 5, 59.0)
    assert not timed.due(0, 30, 0, 600.0) and not Autosave(10, 0.1).due(0, 30, 5, 600.0)


def test_the_object_map_is_rebuilt_at_most_every_period_and_share_of_the_time():
    clock = _Clock()
    throttle = Throttle(period_s=1.0, cpu_share=0.2, clock=clock)
    assert not throttle.due()                                      # nothing changed
    throttle.pending = True
    assert throttle.due()
    throttle.done(0.3)                                             # a 0.3 s rebuild: at most every 1.5 s
    throttle.pending = True
    clock.now = 1.4
    assert not throttle.due()
    clock.now = 1.5
    assert throttle.due()


def test_a_tick_says_what_changed_and_autosaves(tmp_path, observations):
    """Keyframes and edges in; the tick after them returns the keyframe poses, the object map
    when due and the autosave written; the next tick, with nothing new, returns nothing. The
    status counts what arrived; closing saves what is unsaved."""
    clock = _Clock()
    config = with_values(MapperNodeConfig(), {'map_path': str(tmp_path / 'map.rfm'),
                                              'autosave_every_n_keyframes': 3, 'idle_full_solve_s': 0.0})
    core = MapperCore(config, clock=clock)
    graph = ViewGraphBuilder(core.mapper.config.matching)
    keyframes, tracks = 0, []
    for obs in observations[:30]:
        keyframe, edges, track = graph.add(obs)
        if keyframe is not None:
            keyframes += 1
            core.keyframe(keyframe.keyframe_id, keyframe.observations, session=7, sequence=keyframes)
        for e in edges:
            core.edge(EdgeRecord.from_edge(e))
        tracks.append(track)
    assert keyframes >= 3
    tick = core.tick()
    ids, poses, stamps = tick.keyframe_poses
    assert len(ids) == len(core.mapper.poses) >= 2 and set(poses) == set(ids) == set(stamps)
    assert tick.object_map is not None and len(tick.object_map[0]) == core.num_objects > 0
    assert tick.saved == str(tmp_path / 'map.rfm') and os.path.exists(tick.saved)
    quiet = core.tick()
    assert quiet.keyframe_poses is None and quiet.object_map is None and quiet.saved is None
    # no new keyframes, frames still localized: saved once autosave_period_s has passed
    for track in tracks:
        core.tracked_frame(track, session=7)
    clock.now = 59.0
    assert core.tick().saved is None
    clock.now = 60.5
    assert core.tick().saved == str(tmp_path / 'map.rfm')
    assert len(read_map(tmp_path / 'map.rfm')['frames']['stamps']) == len(core.mapper.frames) > 0
    clock.now = 200.0
    assert core.tick().saved is None                                # nothing new since
    status = core.status()
    assert (status.mode, status.num_keyframes, status.num_lost) == ('mapping', len(core.mapper.keyframes), 0)
    core.keyframe(99, None, session=7, sequence=keyframes + 3)      # a malformed one; two never arrived
    assert core.status().num_lost == 2 and 'never arrived' in core.status().message
    # services answer with the response's fields
    assert core.set_mode(5) == {'success': False, 'message': 'unknown mode 5: 0 mapping, 1 localization'}
    assert core.save('../outside.rfm')['success'] is False
    answer = core.load('nothing.rfm')
    assert answer['success'] is False and 'unchanged' in answer['message']
    for obs in observations[30:]:                                   # more keyframes, not yet saved
        keyframe, edges, _ = graph.add(obs)
        if keyframe is not None:
            core.keyframe(keyframe.keyframe_id, keyframe.observations)
    assert list(tmp_path.glob('map.rfm.*.frames'))                   # autosaves append the frames beside it
    saved = core.close()
    assert saved == str(tmp_path / 'map.rfm')
    assert not list(tmp_path.glob('map.rfm.*.frames'))               # stopped: one self-contained file
    loaded = MapperCore(with_values(config, {'load_map_on_start': True}), clock=clock)
    assert len(loaded.mapper.keyframes) == len(core.mapper.keyframes)
    assert loaded.tick().log and loaded.tick().log == []            # 'loaded ...' once
    np.testing.assert_equal(sorted(loaded.mapper.keyframes), sorted(core.mapper.keyframes))


def test_map_to_odom_never_goes_out_twice_at_one_stamp(tmp_path):
    """tf2 keeps only the first transform of a stamp: re-published ahead at 10 Hz with a 0.1 s
    tolerance, the held map -> odom goes out just short of the next image's stamp, where that
    image's own goes; and none goes out twice at one stamp."""
    from rfm_core.session import CameraPose
    core = MapperCore(with_values(MapperNodeConfig(), {'map_path': str(tmp_path / 'map.rfm'),
                                                        'transform_tolerance_s': 0.1}), clock=_Clock())
    core.transform('odom', 'base_link', 0, np.eye(4), False)
    core.transform('odom', 'base_link', 2 * 10**9, np.eye(4), False)
    core.transform('base_link', 'camera_optical', 0, np.eye(4), True)
    first = core.attach(CameraPose(10**9, 'camera_optical', np.eye(4)))
    assert first.child == 'odom' and first.stamp_ns == 10**9
    _, ahead = core.held_transform(now_ns=10**9)
    assert ahead == 11 * 10**8 - 1
    second = core.attach(CameraPose(11 * 10**8, 'camera_optical', np.eye(4)))
    assert second.stamp_ns == 11 * 10**8
    again = core.attach(CameraPose(11 * 10**8, 'camera_optical', np.eye(4)))     # the same image twice
    assert again.stamp_ns == 11 * 10**8 + 1


def test_the_map_waits_for_a_late_mount_before_taking_the_camera_frame_as_its_child():
    """The first camera poses come before the latched /tf_static (discovery is slow under
    load): the map is not broadcast for camera_tf_wait_s, and once the mount arrives it
    attaches to the root of the camera's tree, the camera frame never getting a second parent."""
    from rfm_core.session import CameraPose
    clock = _Clock()
    core = MapperCore(MapperNodeConfig(), clock=clock)
    assert core.attach(CameraPose(10**9, 'camera_optical', np.eye(4))) is None
    clock.now = 0.9 * MapperNodeConfig().camera_tf_wait_s
    assert core.attach(CameraPose(2 * 10**9, 'camera_optical', np.eye(4))) is None
    core.transform('camera_link', 'camera_optical', 0, np.eye(4), True)                # the mount, late
    assert core.attach(CameraPose(3 * 10**9, 'camera_optical', np.eye(4))).child == 'camera_link'
    assert any('waiting' in line for line in core.tick().log)


def test_a_camera_without_tf_gets_the_map_as_its_parent_and_its_own_broadcast_never_takes_its_place():
    """A camera frame still without /tf after camera_tf_wait_s: the map attaches to it. The
    map's broadcast heard back does not make the camera frame the root for good: a mount that
    arrives later still moves the map up to the root of the camera's tree."""
    from rfm_core.session import CameraPose
    clock = _Clock()
    core = MapperCore(MapperNodeConfig(), clock=clock)
    assert core.attach(CameraPose(10**9, 'camera_optical', np.eye(4))) is None
    clock.now = MapperNodeConfig().camera_tf_wait_s
    first = core.attach(CameraPose(2 * 10**9, 'camera_optical', np.eye(4)))
    assert first.child == 'camera_optical'
    core.transform('map', 'camera_optical', first.stamp_ns, first.matrix, False)      # its own, heard back
    core.transform('camera_link', 'camera_optical', 0, np.eye(4), True)                # the mount, later still
    assert core.attach(CameraPose(3 * 10**9, 'camera_optical', np.eye(4))).child == 'camera_link'


def _camera_poses(core, observations) -> list:
    """The camera poses the mapper hands out for ``observations`` fed through a view graph as
    the matcher feeds them, each as it goes out."""
    graph = ViewGraphBuilder(core.mapper.config.matching)
    out = []
    for obs in observations:
        keyframe, edges, track = graph.add(obs)
        if keyframe is not None:
            core.keyframe(keyframe.keyframe_id, keyframe.observations, edges=len(edges))
        for e in edges:
            core.edge(EdgeRecord.from_edge(e))
        out.append(core.tracked_frame(track))
        tick = core.tick()
        out += [*tick.earlier, tick.camera]
    return [c for c in out if c is not None]


def test_separate_views_get_no_tf_of_their_own_and_a_stream_does(observations):
    """tf2 interpolates between two broadcasts: between two photos that would put the camera
    where no measurement did, at every photo the map did not place. A photo collection's poses
    go out on rfm/camera_pose and not on /tf (said once); a handheld stream's go out on both,
    and a robot's odometry carries the camera between separate views, so its map -> odom does."""
    from rfm_core.session import CameraPose
    photos = detected_frames(seed=41, frames=14, capture='sparse')
    for frames, stream in ((observations[:20], True), (photos, False)):
        core = MapperCore(with_values(MapperNodeConfig(), {'idle_full_solve_s': 0.0}), clock=_Clock())
        core.transform('camera_link', frames[0].frame_id, 0, np.eye(4), True)          # the camera's mount
        cameras = _camera_poses(core, frames)
        assert len(cameras) >= 5 and all(c.stream == stream for c in cameras[1:])
        attached = [core.attach(c) for c in cameras]
        if stream:
            assert all(a is not None and a.child == 'camera_link' for a in attached[1:])
        else:
            assert attached == [None] * len(cameras)
            said = [line for line in core.tick().log if 'separate views' in line]
            assert len(said) == 1 and 'rfm/camera_pose' in said[0]
    core = MapperCore(MapperNodeConfig(), clock=_Clock())
    core.transform('odom', 'base_link', 0, np.eye(4), False)
    core.transform('odom', 'base_link', 2 * 10**9, np.eye(4), False)
    core.transform('base_link', 'camera_optical', 0, np.eye(4), True)
    assert core.attach(CameraPose(10**9, 'camera_optical', np.eye(4), stream=False)).child == 'odom'
