"""The detector node with real rclpy: images in, FrameDetections out; bad input dropped."""
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from rfm_core.geometry import iou_3d  # noqa: E402
from rfm_core.io.images import numpy_to_image  # noqa: E402
from rfm_core.io.messages import ROS, camera_info_msg, frame_detections_from_msg, header, imu_msg  # noqa: E402
from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: E402

pytestmark = pytest.mark.ros
FRAME = 'camera_color_optical_frame'


@pytest.fixture(scope='module')
def scene():
    cap = Capture(CaptureConfig(seed=12, frames=10, fps=2))
    return cap, list(cap.frames())


@pytest.fixture
def graph():
    """A detector node and a test node spinning in a background executor."""
    from rfm_detector_node.detector_node import DetectorNode
    from rfm_msgs.msg import FrameDetections
    from sensor_msgs.msg import CameraInfo, Image, Imu
    from diagnostic_msgs.msg import DiagnosticArray

    rclpy.init()
    nodes = {}

    def start(**params):
        # the IMU and the images travel on separate topics; on a loaded machine the first IMU
        # sample can land after the images, beyond the default 50 ms wait
        params.setdefault('imu_wait_s', 1.0)
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        detector = DetectorNode(parameter_overrides=overrides)
        test = Node('detector_test')
        reliable = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        got, diags = [], []
        test.create_subscription(FrameDetections, 'rfm/detections', got.append, reliable)
        test.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
        pubs = {'rgb': test.create_publisher(Image, 'rgb/image', reliable),
                'info': test.create_publisher(CameraInfo, 'rgb/camera_info', reliable),
                'depth': test.create_publisher(Image, 'depth/image', reliable),
                'imu': test.create_publisher(Imu, 'imu', reliable)}
        executor = MultiThreadedExecutor()
        executor.add_node(detector)
        executor.add_node(test)
        thread = threading.Thread(target=executor.spin, daemon=True)
        thread.start()
        nodes.update(detector=detector, test=test, executor=executor, thread=thread)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in pubs.values()):
            time.sleep(0.05)
        return detector, pubs, got, diags

    yield start
    if nodes:
        nodes['executor'].shutdown()
        nodes['thread'].join(timeout=5)     # the spin thread must be out before nodes go
        nodes['detector'].destroy_node()
        nodes['test'].destroy_node()
    rclpy.try_shutdown()


def publish_frame(pubs, cap, frame, stamp=None, rgb_encoding='rgb8', depth_encoding='32FC1',
                  imu=True, info=None, depth=None, rgb=None):
    stamp = frame.stamp_ns if stamp is None else stamp
    if imu:
        force = frame.rotation.T @ np.array([0.0, 0.0, 9.81])
        for dt in (-0.2, -0.1, 0.0):
            pubs['imu'].publish(imu_msg(force, np.zeros(3), stamp + int(dt * 1e9), FRAME))
    h = header(ROS, stamp, FRAME)
    pixels = frame.render.rgb if rgb is None else rgb
    if rgb_encoding == 'bgr8':
        pixels = pixels[..., ::-1]
    pubs['rgb'].publish(numpy_to_image(pixels, rgb_encoding, h))
    pubs['info'].publish(info or camera_info_msg(cap.intrinsics, stamp, FRAME))
    d = frame.render.depth if depth is None else depth
    if depth_encoding == '16UC1':
        d = np.where(np.isfinite(d), np.rint(d * 1000), 0).astype(np.uint16)
    pubs['depth'].publish(numpy_to_image(d.astype(np.float32) if depth_encoding == '32FC1' else d,
                                         depth_encoding, h))


def wait_for(predicate, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def slower_than_the_camera(detector):
    """Make the detector slower than the camera, whatever the machine: its first frame is held
    until a frame arriving behind it has pushed an older one out of the backlog (10 s at most),
    so the burst that follows always finds the worker busy."""
    detect, held = detector.frontend.detect, []

    def held_first(*args, **kwargs):
        if not held:
            held.append(True)
            wait_for(lambda: detector.counts['dropped_busy'] >= 1, timeout=10.0)
        return detect(*args, **kwargs)
    detector.frontend.detect = held_first


def settle(detector, got, newest: int, at_least: int) -> None:
    """Until a burst is through: the newest frame goes out last, but a sensor-data topic may
    lose one of a burst's images on a loaded machine (then the newest that arrived whole is
    the last). Waits for the newest, then for nothing more to come."""
    wait_for(lambda: detector.worker.idle and any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == newest
                                                  for m in got), timeout=10.0)
    n = len(got)
    time.sleep(0.5)
    assert detector.worker.idle and len(got) == n >= at_least, (detector.counts, len(got))


def test_detections_from_bgr8_and_32fc1_in_the_camera_frame(graph, scene):
    cap, frames = scene
    detector, pubs, got, _ = graph(imu_tau_s=0.02)    # the test's IMU jumps between frames
    for frame in frames[:3]:
        publish_frame(pubs, cap, frame, rgb_encoding='bgr8', depth_encoding='32FC1')
        n = len(got)
        assert wait_for(lambda: len(got) > n), 'no FrameDetections received'
    matched = 0
    for msg, frame in zip(got, frames):
        assert msg.header.frame_id == FRAME
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == frame.stamp_ns
        assert msg.backend == 'depth_clusters' and len(msg.detections) > 0
        obs = frame_detections_from_msg(msg)
        gt = frame.ground_truth
        np.testing.assert_allclose(obs.gravity_cam, gt.gravity_cam, atol=0.02)  # from the IMU
        iou = iou_3d(obs.boxes, gt.boxes)
        matched += int(np.count_nonzero(iou.max(1) >= 0.25))
    assert matched >= 6          # boxes land on the true objects: the frames are right


def test_classes_go_out_in_nyu40_names_renamed_by_label_map(graph, scene):
    from rfm_core.detection.labels import NYU40, TO_NYU40

    cap, frames = scene
    with pytest.raises(ValueError, match='spaceship'):
        graph(label_map='spaceship:car')
    renames = ','.join(f'{name}:{name.replace(" ", "_")}_renamed' for name in sorted(set(TO_NYU40.values())))
    _, pubs, got, _ = graph(imu_tau_s=0.02, label_map=renames)
    publish_frame(pubs, cap, frames[0])
    assert wait_for(lambda: got), 'no FrameDetections received'
    labels = [d.label for d in got[0].detections]
    assert labels and all(lab.endswith('_renamed') and lab[:-8].replace('_', ' ') in NYU40 for lab in labels), labels


def test_frames_it_is_behind_on_go_out_with_their_depth_points_only(graph, scene):
    """A burst of 30 Hz frames while the worker detects one: the oldest beyond
    points_only_backlog (3 here) are dropped, each taken while another waits is sent with its
    depth points and no detections, and the newest is detected in full; every frame sent in
    stamp order."""
    cap, frames = scene
    detector, pubs, got, _ = graph(imu_tau_s=0.02, points_only_backlog=3)
    slower_than_the_camera(detector)
    stamps = [frames[0].stamp_ns + i * 33_000_000 for i in range(6)]        # a 30 Hz camera
    for i, stamp in enumerate(stamps):
        publish_frame(pubs, cap, frames[i // 3], stamp=stamp)
    settle(detector, got, stamps[-1], at_least=3)
    sent = [frame_detections_from_msg(m) for m in got]
    assert [o.stamp_ns for o in sent] == sorted(o.stamp_ns for o in sent)
    points_only = [o for o in sent if len(o) == 0]
    assert points_only and all(len(o.cloud) > 100 for o in points_only)
    assert len(sent[-1]) > 0                          # the newest (nothing waits after it): in full
    assert detector.counts['points_only'] == len(points_only) and detector.counts['dropped_busy'] >= 1


def test_on_a_robot_frames_it_has_no_time_for_go_out_with_their_odometry(graph, scene):
    """The same burst on a robot (odometry on /tf): a frame pushed out of the backlog is
    sent with the camera's pose in the odometry frame and nothing else (no detections, no
    depth points: the matcher carries it on the odometry), in stamp order with the rest."""
    cap, frames = scene
    detector, pubs, got, _ = graph(imu_tau_s=0.02, points_only_backlog=1)
    slower_than_the_camera(detector)
    stamps = [frames[0].stamp_ns + i * 33_000_000 for i in range(6)]
    for i, stamp in enumerate(stamps + [stamps[-1] + 33_000_000]):   # as /tf gives it: odom -> camera
        moved = np.eye(4)
        moved[0, 3] = 0.01 * i
        detector.frontend.add_transform('odom', FRAME, stamp, moved)
    for i, stamp in enumerate(stamps):
        publish_frame(pubs, cap, frames[i // 3], stamp=stamp)
    settle(detector, got, stamps[-1], at_least=2)
    sent = [frame_detections_from_msg(m) for m in got]
    assert [o.stamp_ns for o in sent] == sorted(o.stamp_ns for o in sent)
    bare = [o for o in sent if len(o) == 0 and len(o.cloud) == 0]
    assert bare and detector.counts['odometry_only'] == len(bare) >= 1
    for o in bare:                                   # the odometry at its own stamp
        assert o.odometry_epoch == 1
        np.testing.assert_allclose(o.odometry[0, 3], 0.01 * stamps.index(o.stamp_ns), atol=1e-6)
    assert all(o.odometry is not None for o in sent)


def test_bad_input_is_dropped_and_the_next_good_frame_served(graph, scene):
    cap, frames = scene
    detector, pubs, got, diags = graph(imu_max_age_s=0.3)
    good = iter(frames)

    def good_frame():
        n = len(got)
        publish_frame(pubs, cap, next(good), depth_encoding='16UC1')
        assert wait_for(lambda: len(got) > n), f'the node stopped serving good frames: {detector.counts}'

    good_frame()
    f = next(good)

    def rejected(publish):
        n = detector.counts['dropped_invalid']
        publish()
        assert wait_for(lambda: detector.counts['dropped_invalid'] > n), detector.counts

    rejected(lambda: publish_frame(pubs, cap, f, rgb=np.zeros((2, 2, 3), np.uint8)))   # size mismatch
    rejected(lambda: publish_frame(pubs, cap, f, stamp=f.stamp_ns + 1000,             # all-NaN depth
                                   depth=np.full(f.render.depth.shape, np.nan, np.float32)))
    zero_info = camera_info_msg(cap.intrinsics, f.stamp_ns + 2000, FRAME)
    zero_info.k = [0.0] * 9
    rejected(lambda: publish_frame(pubs, cap, f, stamp=f.stamp_ns + 2000, info=zero_info))  # zero K

    def wrong_encoding():
        wrong = numpy_to_image(f.render.rgb, 'rgb8', header(ROS, f.stamp_ns + 3000, FRAME))
        wrong.encoding = 'yuv422'
        pubs['rgb'].publish(wrong)
        pubs['info'].publish(camera_info_msg(cap.intrinsics, f.stamp_ns + 3000, FRAME))
        pubs['depth'].publish(numpy_to_image(f.render.depth, '32FC1', header(ROS, f.stamp_ns + 3000, FRAME)))
    rejected(wrong_encoding)
    assert len(got) == 1
    before = dict(detector.counts)
    old = frames[0]
    publish_frame(pubs, cap, old)                           # out of order (older than the last)
    late = next(good)
    publish_frame(pubs, cap, late, stamp=late.stamp_ns, imu=False)   # no recent IMU
    assert wait_for(lambda: detector.counts['dropped_out_of_order'] > before['dropped_out_of_order']
                    and detector.counts['dropped_no_gravity'] > before['dropped_no_gravity']), \
        f'{before} -> {detector.counts}'
    good_frame()                                             # and it keeps going
    assert wait_for(lambda: any(
        any(kv.key == 'dropped_invalid' and int(kv.value) >= 4 for kv in d.status[0].values)
        for d in diags), timeout=5)


@pytest.mark.slow
def test_ground_truth_backend_republishes_noisy_ground_truth(graph, scene):
    from rfm_core.io.messages import frame_detections_to_msg
    from rfm_msgs.msg import FrameDetections
    cap, frames = scene
    detector, pubs, got, _ = graph(backend='ground_truth', **{'ground_truth.preset': 'rgbd'})
    pub = detector.create_publisher(FrameDetections, 'ground_truth/detections', 10)
    assert wait_for(lambda: pub.get_subscription_count() > 0)
    for frame in frames[:3]:
        n = len(got)
        pub.publish(frame_detections_to_msg(frame.ground_truth))
        assert wait_for(lambda: len(got) > n)
    for msg, frame in zip(got, frames):
        obs = frame_detections_from_msg(msg)
        assert msg.backend == 'ground_truth:rgbd' and len(obs) > 0
        assert np.median(iou_3d(obs.boxes, frame.ground_truth.boxes).max(1)) > 0.5
