"""The committed demo bag: regenerable (the same messages on any CPU), and plays without drops at 1x."""
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


#: Floats may differ in their last bits between CPUs (numpy's SIMD paths): relative tolerance.
FLOAT_RTOL = 1e-7
FLOAT_ATOL = 1e-9
#: ... and so may a rendered pixel, by a level where a float lands on a rounding edge: decoded
#: images compare within this many levels (colour) or millimetres (depth)
PIXEL_TOLERANCE = 2


def _same(a, b, where: str) -> list:
    """Differences between two deserialised messages: images decoded, to PIXEL_TOLERANCE;
    other byte or integer arrays exactly, floats to FLOAT_RTOL; returns descriptions (empty:
    the same)."""
    import numpy as np
    if hasattr(a, 'encoding') and hasattr(a, 'data') and hasattr(a, 'step'):       # an image: decoded
        from rfm_core.io.images import depth_to_meters, image_to_rgb
        fields = lambda m: {f: getattr(m, f) for f in m.__dataclass_fields__ if f != 'data'}  # noqa: E731
        out = _same(fields(a), fields(b), where)
        decode = (lambda m: 1000.0 * depth_to_meters(m)) if a.encoding in ('16UC1', '32FC1') else image_to_rgb
        x, y = np.asarray(decode(a), float), np.asarray(decode(b), float)
        if x.shape != y.shape or np.nanmax(np.abs(x - y), initial=0.0) > PIXEL_TOLERANCE:
            out.append(f'{where}: images differ by more than {PIXEL_TOLERANCE}')
        return out
    if isinstance(a, dict):
        return [d for k in a for d in _same(a[k], b.get(k), f'{where}.{k}')]
    if hasattr(a, '__dataclass_fields__'):
        out = []
        for name in a.__dataclass_fields__:
            out += _same(getattr(a, name), getattr(b, name), f'{where}.{name}')
        return out
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return [f'{where}: {len(a)} vs {len(b)} items']
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _same(x, y, f'{where}[{i}]')]
    if isinstance(a, np.ndarray) or isinstance(a, float):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype != b.dtype:
            return [f'{where}: shape/dtype {a.shape} {a.dtype} vs {b.shape} {b.dtype}']
        if a.dtype.kind == 'f':
            ok = np.allclose(a, b, rtol=FLOAT_RTOL, atol=FLOAT_ATOL, equal_nan=True)
        else:
            ok = np.array_equal(a, b)
        return [] if ok else [f'{where}: values differ (max |a - b| {np.max(np.abs(a.astype(float) - b.astype(float)))})']
    return [] if a == b else [f'{where}: {a!r} vs {b!r}']


def _messages(bag):
    from rosbags.highlevel import AnyReader
    with AnyReader([bag]) as reader:
        return [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype))
                for c, t, raw in reader.messages()]


@pytest.mark.slow
def test_make_demo_regenerates_the_committed_bag(tmp_path):
    """Same topics and stamps, images and depth within a level or two, and the same numbers
    (to the last few bits, which differ between CPUs) as the committed bag; the same
    configuration."""
    import yaml
    out = tmp_path / 'demo'
    subprocess.run([str(ROOT / 'bags' / 'make_demo.sh'), str(out)], check=True,
                   capture_output=True)
    ours, committed = _messages(out), _messages(DEMO)
    assert [m[:3] for m in ours] == [m[:3] for m in committed]
    diffs = [d for (topic, _, t, a), (_, _, _, b) in zip(ours, committed) for d in _same(a, b, f'{topic}@{t}')]
    assert not diffs, diffs[:10]
    def info(bag):
        return yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info(out)['custom_data'] == info(DEMO)['custom_data']
    assert (DEMO / 'demo.mcap').stat().st_size < 8_000_000


def test_message_comparison_tells_float_noise_from_a_changed_value():
    import numpy as np
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    Vector3 = store.types['geometry_msgs/msg/Vector3']
    assert not _same(Vector3(x=1.0, y=2.0, z=3.0), Vector3(x=1.0 + 1e-13, y=2.0, z=3.0), 'v')
    assert _same(Vector3(x=1.0, y=2.0, z=3.0), Vector3(x=1.001, y=2.0, z=3.0), 'v')
    assert _same(np.array([1, 2], np.uint8), np.array([1, 3], np.uint8), 'bytes')
    Image, Header, Time = (store.types[t] for t in ('sensor_msgs/msg/Image', 'std_msgs/msg/Header',
                                                     'builtin_interfaces/msg/Time'))
    def image(pixels):
        return Image(header=Header(stamp=Time(sec=1, nanosec=0), frame_id='c'), height=1, width=2, encoding='rgb8',
                     is_bigendian=0, step=6, data=np.array(pixels, np.uint8))
    assert not _same(image([10, 20, 30, 40, 50, 60]), image([11, 20, 30, 40, 50, 58]), 'image')    # a level or two
    assert _same(image([10, 20, 30, 40, 50, 60]), image([10, 20, 30, 40, 50, 90]), 'image')


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


@pytest.mark.slow
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
        play_bag(node, DEMO, '--wait-for', TOPICS['color'], TOPICS['depth'], TOPICS['imu'], TOPICS['gt_detections'],
                 timeout=90)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert counts == {'color': 100, 'depth': 100, 'imu': 1981, 'gt': 100}, _lost_imu(imu_stamps)
    assert stamps == sorted(stamps)
