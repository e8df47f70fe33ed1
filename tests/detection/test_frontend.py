"""The detector node's front end without ROS: a simulated bag's messages in stamp order,
gravity from its IMU, frames out of order dropped, a looping bag resets, newest frame wins."""
import threading

import numpy as np
import pytest

from rfm_core.detection import make_detector
from rfm_core.detection.frontend import DetectorFrontend, FrameWorker
from rfm_core.sim.capture import TOPICS, Capture, CaptureConfig

rosbags = pytest.importorskip('rosbags')


@pytest.fixture(scope='module')
def bag_messages(tmp_path_factory):
    from rosbags.highlevel import AnyReader
    path = tmp_path_factory.mktemp('bags') / 'frontend'
    capture = Capture(CaptureConfig(seed=44, frames=6, fps=5))
    capture.write_bag(path)
    with AnyReader([path]) as reader:
        messages = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    return messages, {f.stamp_ns: f for f in capture.frames()}


def _feed(frontend, messages, imu=True):
    index = {TOPICS['color']: 0, TOPICS['color_info']: 1, TOPICS['depth']: 2}
    for topic, msg in messages:
        if topic in index:
            frontend.add_image(index[topic], msg)
        elif topic == TOPICS['imu'] and imu:
            frontend.add_imu(msg)


def test_frames_are_synchronised_and_detected_with_the_imus_gravity(bag_messages):
    messages, truth = bag_messages
    frames = []
    frontend = DetectorFrontend(make_detector('depth_clusters'), lambda *job: frames.append(job), imu_wait_s=0.0)
    _feed(frontend, messages)
    assert len(frames) == len(truth) and frontend.counts['received'] == len(truth)
    for job in frames[-2:]:
        obs = frontend.detect(*job)
        true = truth[obs.stamp_ns]
        down = true.pose_matrix[:3, :3].T @ np.array([0.0, 0.0, -1.0])        # world down in the camera
        assert np.degrees(np.arccos(np.clip(obs.gravity_cam @ down, -1, 1))) < 2.0
        assert len(obs) > 0 and obs.imu_rotation is not None and obs.imu_epoch > 0
    # the same frames again: older than the last, dropped as out of order
    _feed(frontend, messages)
    assert len(frames) == len(truth) and frontend.counts['dropped_out_of_order'] == len(truth)


def test_without_imu_frames_are_dropped_and_a_fixed_gravity_serves(bag_messages):
    messages, truth = bag_messages
    frames = []
    frontend = DetectorFrontend(make_detector('depth_clusters'), lambda *job: frames.append(job), imu_wait_s=0.0)
    _feed(frontend, messages, imu=False)
    assert frontend.detect(*frames[0]) is None and frontend.counts['dropped_no_gravity'] == 1
    fixed = DetectorFrontend(make_detector('depth_clusters'), lambda *job: None, fixed_gravity=[0.0, 2.0, 0.0])
    obs = fixed.detect(*frames[0])
    assert np.allclose(obs.gravity_cam, [0.0, 1.0, 0.0]) and obs.imu_rotation is None
    with pytest.raises(ValueError, match='non-zero'):
        DetectorFrontend(make_detector('depth_clusters'), lambda *job: None, fixed_gravity=[0.0, 0.0, 0.0])


def test_a_frame_taken_late_keeps_its_gravity(bag_messages):
    """A frame the detector takes after the IMU has run on past it by more than
    imu_max_age_s is not stale: it gets gravity as it was at its stamp, not dropped."""
    messages, truth = bag_messages
    frames = []
    frontend = DetectorFrontend(make_detector('depth_clusters'), lambda *job: frames.append(job), imu_wait_s=0.0,
                                imu_max_age_s=0.3)
    _feed(frontend, messages)
    first = min(truth)
    assert (frontend.gravity_filter.last_stamp_ns - first) * 1e-9 > 0.6          # the IMU is far past it
    obs = frontend.detect(*frames[0])
    assert obs is not None and obs.stamp_ns == first and frontend.counts['dropped_no_gravity'] == 0
    down = truth[first].pose_matrix[:3, :3].T @ np.array([0.0, 0.0, -1.0])
    assert np.degrees(np.arccos(np.clip(obs.gravity_cam @ down, -1, 1))) < 2.0


def test_a_frame_taken_seconds_late_keeps_the_gyroscopes_orientation(tmp_path):
    """A detector behind its camera (a slow machine) takes a frame after seconds of IMU
    samples have come in since: the frame still gets the gyroscope's orientation at its stamp
    (the gyroscope's yaw edges of the map need it) and its gravity as it was then."""
    from rosbags.highlevel import AnyReader

    from rfm_core.observations import imu_relative_yaw

    capture = Capture(CaptureConfig(seed=45, frames=16, fps=5))                 # 3 s: 600 IMU samples
    capture.write_bag(tmp_path / 'late')
    truth = {f.stamp_ns: f for f in capture.frames()}
    with AnyReader([tmp_path / 'late']) as reader:
        messages = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    frames = []
    frontend = DetectorFrontend(make_detector('depth_clusters'), lambda *job: frames.append(job), imu_wait_s=0.0)
    _feed(frontend, messages)
    first, last = frontend.detect(*frames[0]), frontend.detect(*frames[-1])
    assert (last.stamp_ns - first.stamp_ns) * 1e-9 > 2.5
    assert first.imu_rotation is not None and first.imu_epoch == last.imu_epoch > 0
    down = truth[first.stamp_ns].pose_matrix[:3, :3].T @ np.array([0.0, 0.0, -1.0])
    assert np.degrees(np.arccos(np.clip(first.gravity_cam @ down, -1, 1))) < 2.0
    aligned = [truth[o.stamp_ns].pose_matrix[:3, :3] @ o.rotation_aligned_from_camera.T for o in (first, last)]
    turn = aligned[0].T @ aligned[1]                                 # the gravity-aligned frames' T_first_last
    true = np.arctan2(turn[1, 0], turn[0, 0])
    assert abs(np.degrees(np.angle(np.exp(1j * (imu_relative_yaw(first, last) - true))))) < 1.0


def test_gravity_long_after_is_not_turned_back_through_the_gyroscopes_drift():
    """A camera at rest, its gyroscope reading 1 deg/s of bias: the gravity of a frame taken
    3 s late is the estimate the filter had then (0.5 deg off), not the newest turned back
    through 3 s of the bias (2 deg off); one taken 0.1 s late is turned back."""
    from rfm_core.detection.gravity import GravityFilter

    down = np.array([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0])
    bias = np.radians([1.0, 0.0, 0.0])
    imu = GravityFilter(rest_reset_deg=45.0)
    for i in range(800):                                             # 4 s at 200 Hz
        imu.add(i * 5_000_000, -GravityFilter.G * down, bias)

    def off(stamp_ns):
        return np.degrees(np.arccos(np.clip(imu.gravity_at(stamp_ns) @ down, -1, 1)))
    assert off(1_000_000_000) < 1.5 and off(3_900_000_000) < 1.5


def test_every_nth_frame_and_a_looping_bag(bag_messages):
    messages, truth = bag_messages
    frames = []
    frontend = DetectorFrontend(make_detector('depth_clusters'), lambda *job: frames.append(job), every_nth_frame=2)
    _feed(frontend, messages)
    assert len(frames) == 3 and frontend.counts['skipped_nth'] == 3
    frontend._last_stamp += 10 ** 10                  # the bag plays again from the start: 10 s back
    _feed(frontend, messages)
    assert frontend.counts['dropped_out_of_order'] == 0 and len(frames) == 6


def _run_worker(backlog: int) -> tuple:
    """Jobs submitted while the worker is blocked on the first: (done, replaced, waiting seen
    by each job, what ran in order with the jobs pushed out, the threads they ran on)."""
    release, done, replaced, waiting, order, threads = threading.Event(), [], [], [], [], set()
    worker = None

    def work(job):
        release.wait(5)
        waiting.append(worker.waiting)
        done.append(job)
        order.append(job)
        threads.add(threading.current_thread().name)

    def pushed_out(job):
        replaced.append(job)
        order.append(f'{job} (pushed out)')
        threads.add(threading.current_thread().name)
    worker = FrameWorker(work, pushed_out, name='test_worker', backlog=backlog)
    worker.submit('first')                            # taken at once, blocks the worker
    deadline = threading.Event()
    while worker.waiting and not deadline.wait(0.01):
        pass
    for job in ('second', 'third', 'fourth'):
        worker.submit(job)
    release.set()
    while not worker.idle and not deadline.wait(0.01):
        pass
    worker.stop()
    return done, len(replaced), waiting, order, threads


def test_the_newest_job_wins_while_the_worker_is_busy():
    done, replaced, waiting, _, _ = _run_worker(backlog=1)
    assert done == ['first', 'fourth'] and replaced == 2 and waiting == [1, 0]


def test_jobs_pushed_out_are_handed_back_on_the_worker_thread_before_later_ones():
    """A frame the detector has no time for goes out (a robot's, with its odometry) before
    the frames after it: stamps stay in order."""
    _, _, _, order, threads = _run_worker(backlog=1)
    assert order == ['first', 'second (pushed out)', 'third (pushed out)', 'fourth'] and threads == {'test_worker'}


def test_a_backlog_keeps_the_newest_jobs_in_order_and_tells_work_it_is_behind():
    done, replaced, waiting, _, _ = _run_worker(backlog=2)
    assert done == ['first', 'third', 'fourth'] and replaced == 1
    assert waiting == [2, 1, 0]                       # each ran with the later ones waiting: behind


def test_a_robots_frame_without_time_for_it_goes_out_with_its_odometry(tmp_path):
    """On a robot a frame the detector pushes out of its backlog is sent with the camera's
    pose in the odometry frame (and gravity, the gyroscope's orientation), no detections
    and no depth points: the matcher carries it on the odometry. Without odometry: nothing."""
    from rosbags.highlevel import AnyReader

    from rfm_core.io.messages import transforms_from_msg

    path = tmp_path / 'robot'
    capture = Capture(CaptureConfig(seed=12, capture='robot', frames=6, fps=5))
    capture.write_bag(path)
    with AnyReader([path]) as reader:
        messages = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    truth = capture.camera_odometry()
    frames = []
    robot = DetectorFrontend(make_detector('depth_clusters'), lambda *job: frames.append(job), imu_wait_s=0.0,
                             odom_frame='odom')
    for topic, msg in messages:
        if topic in (TOPICS['tf'], TOPICS['tf_static']):
            for link in transforms_from_msg(msg):
                robot.add_transform(*link, topic == TOPICS['tf_static'])
    _feed(robot, messages)
    obs = robot.odometry_only(*frames[-1])
    assert obs is not None and len(obs) == 0 and len(obs.cloud) == 0 and obs.imu_epoch > 0
    np.testing.assert_allclose(obs.odometry, truth[obs.stamp_ns], atol=1e-4)   # the bag's odometry at the image
    assert robot.counts['odometry_only'] == 1 and robot.counts['processed'] == 0
    handheld = DetectorFrontend(make_detector('depth_clusters'), lambda *job: None, imu_wait_s=0.0, odom_frame='odom')
    _feed(handheld, messages)
    assert handheld.odometry_only(*frames[-1]) is None            # no odometry on /tf: dropped as before


def test_a_robots_drive_does_not_tilt_gravity(tmp_path):
    """A drive's start and stop add up to 1-2 m/s^2 to the accelerometer, which tilts the
    IMU's gravity. With the camera's acceleration from the odometry on /tf taken out, gravity
    stays within a degree at every frame, and most frames' error falls by 4x or more."""
    from rosbags.highlevel import AnyReader

    from rfm_core.evaluation.report import read_ground_truth
    from rfm_core.io.messages import stamp_to_ns, transforms_from_msg

    path = tmp_path / 'robot'
    capture = Capture(CaptureConfig(seed=13, capture='robot', frames=60, fps=4, width=32, height=24))
    capture.write_bag(path)
    with AnyReader([path]) as reader:
        messages = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    down = {stamp: pose[:3, :3].T @ [0.0, 0.0, -1.0] for stamp, pose in read_ground_truth(path).camera_poses.items()}

    def gravity_errors(odom_frame):
        frontend = DetectorFrontend(make_detector('depth_clusters'), lambda *job: None, imu_wait_s=0.0,
                                    odom_frame=odom_frame)
        stamps, errors = [], []
        for topic, msg in messages:
            if topic in (TOPICS['tf'], TOPICS['tf_static']):
                for link in transforms_from_msg(msg):
                    frontend.add_transform(*link, topic == TOPICS['tf_static'])
            elif topic == TOPICS['imu']:
                frontend.add_imu(msg)
            elif topic == TOPICS['color']:
                frontend.add_image(0, msg)
                stamps.append(stamp_to_ns(msg.header.stamp))
            while stamps and (frontend.gravity_filter.last_stamp_ns or 0) >= stamps[0]:
                stamp = stamps.pop(0)
                cos = frontend.gravity_filter.gravity_at(stamp) @ down[stamp]
                errors.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        return np.array(errors)

    imu_only, with_odometry = gravity_errors(''), gravity_errors('odom')
    assert len(with_odometry) >= 55 and len(imu_only) >= 55
    assert np.percentile(imu_only, 90) > 0.3                 # the drives tilt the IMU's gravity
    assert with_odometry.max() < 1.0 and np.percentile(with_odometry, 90) < 0.25 * np.percentile(imu_only, 90)
