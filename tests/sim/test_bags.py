"""Simulated captures written as rosbag2 MCAP bags that standard readers open."""
import json
from pathlib import Path

import numpy as np
import pytest

from rfm_core.io.images import depth_to_meters, image_to_numpy
from rfm_core.io.messages import frame_detections_from_msg, stamp_to_ns
from rfm_core.sim.capture import START_NS, TOPICS, Capture, CaptureConfig

CONFIG = dict(seed=21, frames=15, fps=10, width=160, height=120, imu_rate_hz=100)


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('bags') / 'scene'
    summary = Capture(CaptureConfig(**CONFIG)).write_bag(path)
    return path, summary


def test_same_seed_gives_identical_bytes(bag, tmp_path):
    path, _ = bag
    again = tmp_path / 'again'
    Capture(CaptureConfig(**CONFIG)).write_bag(again)
    for name in ('scene.mcap', 'metadata.yaml'):
        other = 'again.mcap' if name == 'scene.mcap' else name
        assert (path / name).read_bytes().replace(b'scene.mcap', b'again.mcap') == (again / other).read_bytes()
    different = tmp_path / 'different'
    Capture(CaptureConfig(**dict(CONFIG, seed=22))).write_bag(different)
    assert (different / 'different.mcap').read_bytes() != (again / 'again.mcap').read_bytes()


def test_rosbags_reads_every_message_with_configured_counts_and_stamps(bag):
    from rosbags.highlevel import AnyReader
    path, summary = bag
    frames, fps = CONFIG['frames'], CONFIG['fps']
    expected_counts = {TOPICS['color']: frames, TOPICS['depth']: frames, TOPICS['color_info']: frames,
                       TOPICS['depth_info']: frames, TOPICS['gt_pose']: frames,
                       TOPICS['gt_detections']: frames, TOPICS['tf_static']: 1,
                       TOPICS['gt_objects']: 1,
                       TOPICS['imu']: int((frames - 1) / fps * CONFIG['imu_rate_hz']) + 1}
    seen = {topic: [] for topic in expected_counts}
    with AnyReader([path]) as reader:          # types come from the bag itself
        assert {c.topic for c in reader.connections} == set(expected_counts)
        latched = {c.topic for c in reader.connections
                   if any(q.durability.name == 'TRANSIENT_LOCAL' for q in c.ext.offered_qos_profiles)}
        assert latched == {TOPICS['tf_static'], TOPICS['gt_objects']}
        previous = 0
        for connection, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            assert timestamp >= previous
            previous = timestamp
            if hasattr(msg, 'header'):
                assert stamp_to_ns(msg.header.stamp) == timestamp
            seen[connection.topic].append((timestamp, msg))
    assert {t: len(v) for t, v in seen.items()} == expected_counts
    stamps = [t for t, _ in seen[TOPICS['color']]]
    assert stamps == [START_NS + round(i / fps * 1e9) for i in range(frames)]
    # payloads decode with the project's own converters
    rgb = image_to_numpy(seen[TOPICS['color']][3][1])
    depth = depth_to_meters(seen[TOPICS['depth']][3][1])
    assert rgb.shape == (120, 160, 3) and depth.shape == (120, 160)
    assert 0.3 < np.nanmedian(depth) < 8.0
    gt = frame_detections_from_msg(seen[TOPICS['gt_detections']][3][1])
    assert len(gt) > 0 and gt.backend == 'ground_truth' and np.all(gt.object_ids > 0)
    objects = seen[TOPICS['gt_objects']][0][1].objects
    assert set(gt.object_ids) <= {o.id for o in objects}
    assert summary['messages'] == expected_counts


def test_mcap_reader_decodes_every_message(bag):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path, summary = bag
    counts = {}
    with open(Path(path) / f'{Path(path).name}.mcap', 'rb') as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            assert decoded is not None
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts == summary['messages']


def test_metadata_records_how_the_bag_was_made(bag):
    from rfm_core.io.bag import bag_custom_data
    path, _ = bag
    config = json.loads(bag_custom_data(path)['rfm.sim.config'])
    assert config['seed'] == CONFIG['seed'] and config['frames'] == CONFIG['frames']
    assert CaptureConfig(**config).to_json() == CaptureConfig(**CONFIG).to_json()


def test_depth_encodings(tmp_path):
    for encoding in ('16UC1', '32FC1'):
        path = tmp_path / encoding
        Capture(CaptureConfig(seed=3, frames=2, width=64, height=48, depth_encoding=encoding)).write_bag(path)
        from rosbags.highlevel import AnyReader
        with AnyReader([path]) as reader:
            conn = [c for c in reader.connections if c.topic == TOPICS['depth']]
            msg = reader.deserialize(next(reader.messages(connections=conn))[2], conn[0].msgtype)
        assert msg.encoding == encoding
        assert 0.3 < np.nanmedian(depth_to_meters(msg)) < 8


def test_bag_reader_pairs_depth_stamped_after_colour(tmp_path):
    """Drivers stamp depth a few ms after colour: the bag reader pairs them by approximate
    time, as the detector node does, and loses no frame."""
    from foreign import foreign_bag

    from rfm_core.io.bag import iter_camera_frames

    src = tmp_path / 'sim'
    Capture(CaptureConfig(seed=2, frames=12, fps=15, width=64, height=48)).write_bag(src)
    bag = foreign_bag(src, tmp_path / 'user', depth_offset_ms=12.0)
    frames = list(iter_camera_frames(bag, '/camera/color/image_raw', '/camera/depth/image_raw',
                                     '/camera/color/camera_info', '/imu/data'))
    assert len(frames) == 12
    for f in frames:
        depth = f['depth'].header.stamp.sec * 10**9 + f['depth'].header.stamp.nanosec
        assert depth - f['stamp_ns'] == 12_000_000
    assert sum(len(f['imu']) for f in frames) > 0


def test_realsense_bags_stamp_depth_after_colour_and_offset_the_imu(tmp_path):
    """The realsense sensor model: depth stamped 3-10 ms after its colour image, IMU stamps
    4 ms late, depth one pixel off colour; the stored config reads back."""
    from rosbags.highlevel import AnyReader

    from rfm_core.io.bag import bag_custom_data
    from rfm_core.sim.render import NoiseModel
    config = CaptureConfig(seed=8, frames=6, fps=5, noise=NoiseModel.realsense())
    Capture(config).write_bag(tmp_path / 'rs')
    stamps = {TOPICS['color']: [], TOPICS['depth']: [], TOPICS['imu']: []}
    with AnyReader([tmp_path / 'rs']) as reader:
        for c, t, raw in reader.messages(connections=[c for c in reader.connections if c.topic in stamps]):
            msg = reader.deserialize(raw, c.msgtype)
            assert stamp_to_ns(msg.header.stamp) == t
            stamps[c.topic].append(t)
    delay = (np.array(stamps[TOPICS['depth']]) - np.array(stamps[TOPICS['color']])) / 1e6
    assert len(delay) == 6 and np.all((delay >= 3.0) & (delay <= 10.0)) and np.ptp(delay) > 0.5
    start = Capture(config).stamp_ns(0.0)
    assert (np.array(stamps[TOPICS['imu']]) - start).min() == 4_000_000      # the first sample, 4 ms late
    frame = next(Capture(config).frames())
    true, noisy = frame.render.depth_true, frame.render.depth
    errors = {}
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            shifted = np.roll(np.roll(true, dy, 0), dx, 1)
            errors[dx, dy] = np.nanmedian(np.abs(noisy - shifted)[2:-2, 2:-2])
    assert min(errors, key=errors.get) != (0, 0)                          # registered a pixel off
    stored = CaptureConfig(**json.loads(bag_custom_data(tmp_path / 'rs')['rfm.sim.config']))
    assert stored.noise == config.noise and stored.to_json() == config.to_json()


def test_a_bags_frames_reach_the_detector_as_the_node_sees_them(bag):
    """``detector_inputs`` gives every n-th frame with gravity from the IMU filter (near the
    simulator's true gravity once it settles) and metric depth; ``evaluate_bag`` scores a
    detector on them against the bag's ground truth (the ground-truth detector: near-perfect)."""
    from rfm_core.detection import make_detector
    from rfm_core.evaluation.detection_bags import detector_inputs, evaluate_bag

    path, _ = bag
    frames = Capture(CaptureConfig(**CONFIG)).frames()
    truth = {f.stamp_ns: f for f in frames}
    seen = list(detector_inputs(path, every=2))
    assert [f['stamp_ns'] for f, _ in seen] == sorted(truth)[::2]
    ready = [inp for _, inp in seen if inp is not None]
    assert len(ready) >= len(seen) - 2
    for inp in ready[2:]:
        down = truth[inp.stamp_ns].rotation.T @ np.array([0.0, 0.0, -1.0])      # gravity in the camera frame
        g = np.asarray(inp.gravity_cam, float)
        assert np.degrees(np.arccos(np.clip(g @ down / np.linalg.norm(g), -1, 1))) < 2.0
        assert inp.depth.shape == (CONFIG['height'], CONFIG['width']) and np.nanmax(inp.depth) < 20.0
    result = evaluate_bag(path, make_detector('ground_truth', preset='perfect'))
    assert result['AP25'] > 0.9 and np.isfinite(result['latency_ms'])
