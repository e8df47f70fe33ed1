"""The committed demo bag: regenerable bit-for-bit, and plays without drops at 1x."""
import subprocess
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from rfm_core.sim.capture import TOPICS  # noqa: E402

from playback import play_bag  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / 'bags' / 'demo'


def test_make_demo_regenerates_the_committed_bag_bit_for_bit(tmp_path):
    out = tmp_path / 'demo'
    subprocess.run([str(ROOT / 'bags' / 'make_demo.sh'), str(out)], check=True,
                   capture_output=True)
    assert (out / 'demo.mcap').read_bytes() == (DEMO / 'demo.mcap').read_bytes()
    assert (out / 'metadata.yaml').read_text() == (DEMO / 'metadata.yaml').read_text()
    assert (DEMO / 'demo.mcap').stat().st_size < 8_000_000


def _lost_imu(received) -> str:
    """Which recorded IMU samples never arrived (the first ones: discovery; scattered:
    delivery): read from the bag only when the test fails."""
    from rosbags.highlevel import AnyReader
    with AnyReader([DEMO]) as reader:
        conns = [c for c in reader.connections if c.topic == TOPICS['imu']]
        stamps = [reader.deserialize(raw, c.msgtype).header.stamp for c, _, raw in reader.messages(connections=conns)]
    recorded = [s.sec * 10**9 + s.nanosec for s in stamps]
    received = set(received)
    lost = [i for i, s in enumerate(recorded) if s not in received]
    return f'lost IMU samples (indices of {len(recorded)}): {lost[:20]}'


@pytest.mark.ros
@pytest.mark.slow
def test_demo_bag_plays_at_1x_without_drops():
    from sensor_msgs.msg import Image, Imu
    from rfm_msgs.msg import FrameDetections
    rclpy.init()
    node = Node('rfm_demo_play_test')
    counts = {'color': 0, 'depth': 0, 'imu': 0, 'gt': 0}
    stamps = []
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)

    def on_color(msg):
        counts['color'] += 1
        stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
    node.create_subscription(Image, TOPICS['color'], on_color, reliable)
    node.create_subscription(Image, TOPICS['depth'], lambda m: counts.__setitem__('depth', counts['depth'] + 1), reliable)
    # best effort, like the recording: a deep queue holds bursts while this process is busy
    imu_stamps = []

    def on_imu(msg):
        counts['imu'] += 1
        imu_stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
    node.create_subscription(Imu, TOPICS['imu'], on_imu,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT))
    node.create_subscription(FrameDetections, TOPICS['gt_detections'],
                             lambda m: counts.__setitem__('gt', counts['gt'] + 1), reliable)
    try:
        play_bag(node, DEMO, timeout=90)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert counts == {'color': 100, 'depth': 100, 'imu': 1981, 'gt': 100}, _lost_imu(imu_stamps)
    assert stamps == sorted(stamps)
