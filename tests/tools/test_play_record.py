"""`rfm play` and `rfm record` with real rclpy processes."""
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402

from rfm_core.sim.capture import TOPICS, Capture, CaptureConfig  # noqa: E402

from playback import play_bag  # noqa: E402

pytestmark = pytest.mark.ros
RFM = shutil.which('rfm')


def bag_messages(path):
    """{topic: [raw bytes, ...]} in bag order."""
    out = {}
    with AnyReader([Path(path)]) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(bytes(raw))
    return out


@pytest.fixture(scope='module')
def small_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('play') / 'small'
    Capture(CaptureConfig(seed=5, frames=20, fps=10, width=96, height=72,
                          imu_rate_hz=50)).write_bag(path)
    return path


@pytest.mark.slow
def test_play_delivers_everything_in_order_with_clock_and_record_replays_identically(small_bag, tmp_path):
    assert RFM, 'rfm is not on PATH: run through ros_ws/env.sh'
    recorded = tmp_path / 'recorded'
    topics = [TOPICS['color'], TOPICS['depth'], TOPICS['imu'], TOPICS['gt_detections'],
              TOPICS['gt_objects'], TOPICS['tf_static']]
    recorder = subprocess.Popen([RFM, 'record', str(recorded), '--topics', *topics],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = Node('rfm_play_test')
    from rfm_msgs.msg import ObjectMap
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image, Imu
    got = {'color': [], 'imu': [], 'clock': [], 'objects': []}
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Image, TOPICS['color'], lambda m: got['color'].append(m), reliable)
    # the IMU is recorded best-effort, as drivers publish it: a reliable subscriber would not match
    node.create_subscription(Imu, TOPICS['imu'], lambda m: got['imu'].append(m),
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    node.create_subscription(Clock, '/clock', lambda m: got['clock'].append(m), reliable)
    node.create_subscription(ObjectMap, TOPICS['gt_objects'], lambda m: got['objects'].append(m),
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                        reliability=ReliabilityPolicy.RELIABLE))
    try:
        # the recorder (another process) discovers the player's topics at 2 Hz: give it time
        # on a loaded machine before the first message
        play_bag(node, small_bag, delay=8.0)
    finally:
        recorder.send_signal(signal.SIGINT)
        try:
            rec_out = recorder.communicate(timeout=20)[0]
        except subprocess.TimeoutExpired:
            recorder.kill()
            rec_out = recorder.communicate()[0]
        node.destroy_node()
        rclpy.try_shutdown()
    assert recorder.returncode == 0, rec_out

    original = bag_messages(small_bag)
    # every message, in order, at 1x
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got['color']]
    assert len(got['color']) == len(original[TOPICS['color']]) == 20
    assert stamps == sorted(stamps)
    assert len(got['imu']) == len(original[TOPICS['imu']])
    assert len(got['objects']) == 1
    # /clock advances to the end of the bag
    clock = [c.clock.sec * 10**9 + c.clock.nanosec for c in got['clock']]
    assert len(clock) > 20 and clock == sorted(clock)
    assert clock[-1] >= stamps[-1]
    # the recording holds the same messages, byte for byte, in the same order
    again = bag_messages(recorded)
    for topic in topics:
        assert again.get(topic) == original[topic], f'{topic} differs after record'


@pytest.mark.slow
def test_play_remaps_filters_and_rate(small_bag):
    rclpy.init()
    node = Node('rfm_play_remap_test')
    from sensor_msgs.msg import Image
    got = []
    arrival = []
    node.create_subscription(Image, '/renamed/rgb', lambda m: (got.append(m), arrival.append(time.monotonic())),
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    seen_topics = set()
    try:
        elapsed = play_bag(node, small_bag, '--rate', '4', '--topics', TOPICS['color'],
                           '--remap', f'{TOPICS["color"]}:=/renamed/rgb', '--wait-for', TOPICS['color'], drain=1.0,
                           on_spin=lambda: seen_topics.update(t for t, _ in node.get_topic_names_and_types()))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert len(got) == 20, [(m.header.stamp.nanosec // 10**8, t - arrival[0]) for m, t in zip(got, arrival)]
    assert TOPICS['depth'] not in seen_topics and TOPICS['color'] not in seen_topics
    assert elapsed < 3 + 1.9 / 4 + 20         # 1.9 s of bag at 4x, plus start-up (slow when loaded)
    assert arrival[-1] - arrival[0] < 1.2     # 1.9 s of images at 4x: ~0.5 s (1.9 s at 1x)


@pytest.mark.slow
def test_paced_play_waits_for_each_image_to_be_answered(small_bag):
    """`rfm play --pace` (`rfm run --paced`): each colour image is published only once the one
    before it is answered (a FrameDetections with its stamp), so a slow consumer loses none
    even at a rate far above what it takes. A consumer that answers 0.3 s after each image:
    the 20 images, 0.1 s apart in the bag, come at least 0.3 s apart at 50x, and each after
    the answer to the one before."""
    from rfm_msgs.msg import FrameDetections
    from sensor_msgs.msg import Image
    rclpy.init()
    node = Node('rfm_pace_test')
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    answers = node.create_publisher(FrameDetections, '/test/answers', reliable)
    arrival, answered, pending = [], [], []

    def on_image(msg):
        arrival.append(time.monotonic())
        pending.append((time.monotonic() + 0.3, msg.header.stamp))

    def answer():
        while pending and pending[0][0] <= time.monotonic():
            _, stamp = pending.pop(0)
            out = FrameDetections()
            out.header.stamp = stamp
            answers.publish(out)
            answered.append(time.monotonic())
    node.create_subscription(Image, TOPICS['color'], on_image, reliable)
    node.create_timer(0.01, answer)
    try:
        play_bag(node, small_bag, '--rate', '50', '--topics', TOPICS['color'], '--wait-for', TOPICS['color'],
                 '--pace', TOPICS['color'], '/test/answers', drain=1.0)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert len(arrival) == 20
    gaps = np.diff(arrival)
    assert gaps.min() >= 0.28, gaps                  # each waited for the answer before it (0.3 s)
    assert all(a >= b - 0.02 for a, b in zip(arrival[1:], answered))      # ... after it, not before
    assert arrival[-1] - arrival[0] < 19 * 0.3 + 3.0  # and no longer: 1.9 s of bag at 50x is 0.04 s


def test_play_waits_for_as_many_subscribers_as_asked(small_bag):
    """`rfm play --wait-for TOPIC=N` (rfm run: /tf and /tf_static for the recorder, the mapper
    and the detector): a subscriber that comes 2 s after the first still gets every message
    (with one asked for, 20 frames at 5x were over in 0.4 s, before it came)."""
    from sensor_msgs.msg import Image
    rclpy.init()
    node = Node('rfm_wait_test')
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    first, second, late = [], [], []
    node.create_subscription(Image, TOPICS['color'], first.append, reliable)
    start = time.monotonic()

    def late_subscriber():
        if not late and time.monotonic() - start > 2.0:
            late.append(node.create_subscription(Image, TOPICS['color'], second.append, reliable))
    try:
        play_bag(node, small_bag, '--rate', '5', '--topics', TOPICS['color'], '--wait-for', f'{TOPICS["color"]}=2',
                 delay=0.0, on_spin=late_subscriber)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert late and len(first) == len(second) == 20


def test_a_subscriber_count_to_wait_for_must_be_a_positive_number():
    from rfm_bringup.player import PlayOptions
    assert PlayOptions(wait_for=['/a', '/tf=3']).wait_for == ['/a', '/tf=3']
    for bad in ('/tf=0', '/tf=x', '/tf=-1'):
        with pytest.raises(ValueError, match='TOPIC=N'):
            PlayOptions(wait_for=[bad])


def test_the_recorder_stops_a_topic_at_its_size_cap(tmp_path):
    """`rfm run --live --record-images MB`: images are recorded up to the cap, the rest of
    the outputs go on (before: every colour image, without limit; #19 row 10)."""
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from rclpy.executors import SingleThreadedExecutor

    from rfm_bringup.recorder import BagRecorder
    rclpy.init()
    try:
        image = Image(height=10, width=100, encoding='rgb8', step=300, data=bytes(3000))
        from rclpy.serialization import serialize_message
        size = len(serialize_message(image))
        node = Node('cap_test')
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        img_pub, txt_pub = node.create_publisher(Image, '/cam', qos), node.create_publisher(String, '/txt', qos)
        recorder = BagRecorder(str(tmp_path / 'out'), topics=['/cam', '/txt'], max_bytes={'/cam': 3.5 * size})
        executor = SingleThreadedExecutor()
        executor.add_node(recorder)
        executor.add_node(node)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not {'/cam', '/txt'} <= set(recorder.counts):
            executor.spin_once(timeout_sec=0.1)
        for i in range(10):
            img_pub.publish(image)
            txt_pub.publish(String(data=str(i)))
            executor.spin_once(timeout_sec=0.05)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and recorder.counts.get('/txt', 0) < 10:
            executor.spin_once(timeout_sec=0.1)
        counts = recorder.close()
        executor.shutdown()
        recorder.destroy_node()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert counts['/cam'] == 3 and counts['/txt'] == 10, counts
    assert recorder.received['/cam'] == 10              # what rfm run counts as frames: every one received
    written = bag_messages(tmp_path / 'out')
    assert len(written['/cam']) == 3 and len(written['/txt']) == 10


def test_preview_streams_the_bag_and_shows_the_picked_frames(small_bag, tmp_path):
    """`rfm preview`: colour | depth of evenly spaced frames (the bag is streamed, not read
    into memory whole: #19 row 10)."""
    from matplotlib.image import imread
    out = tmp_path / 'sheet.png'
    done = subprocess.run([RFM, 'preview', str(small_bag), str(out), '--frames', '3'],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert 'frames [0, 10, 19] of 20' in done.stdout
    assert imread(out).shape[:2] == (3 * 72, 2 * 96)
