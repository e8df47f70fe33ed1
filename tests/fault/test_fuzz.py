"""Hostile input for every node (#19 item 2): every subscription and service of the
detector, matcher and mapper, called with malformed messages; no node may raise or count an
unexpected error (their guards would hide one), their timers then run cleanly, and each keeps
serving good input afterwards, with no reset.

Messages start from every field filled at random (extreme integers included) and are then
mutated: floats to NaN / inf / huge, sequences emptied or grown to hundreds of elements,
stamps repeated or sent backwards, strings long and odd. The callbacks are called as the
executor would call them (an exception there kills a node's spin). ``RFM_FUZZ_N`` sets the
number of hostile inputs (``make fuzz``: 10,000; the test suite: a seeded few hundred)."""
import inspect
import math
import os
import random
import sys
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.parameter import Parameter  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'ros'))
from msg_fill import fill  # noqa: E402

from sim_frames import detected_frames  # noqa: E402

from rfm_core.io.messages import frame_detections_to_msg  # noqa: E402

pytestmark = pytest.mark.ros
N = int(os.environ.get('RFM_FUZZ_N', '400'))
SEED = int(os.environ.get('RFM_FUZZ_SEED', '19'))
ODD = [math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -0.0, 1e-320]


def _mutate(msg, rng: random.Random, depth: int = 0):
    """Set some fields of ``msg`` (recursively) to hostile values; returns ``msg``."""
    for name, kind in msg.get_fields_and_field_types().items():
        if rng.random() > 0.35:
            continue
        value = getattr(msg, name)
        try:
            if kind in ('float', 'double'):
                setattr(msg, name, rng.choice(ODD))
            elif kind == 'string':
                setattr(msg, name, rng.choice(['', 'x' * 5000, '../../etc/passwd', '\u2603\x00?']))
            elif kind.startswith('sequence<float') or kind.startswith('sequence<double'):
                n = rng.choice([0, 1, 7, 257, 5000])
                setattr(msg, name, [rng.choice(ODD + [1.0]) for _ in range(n)])
            elif kind.startswith('sequence<') and depth < 3 and hasattr(value, '__len__') and len(value):
                item = value[0]
                if hasattr(item, 'get_fields_and_field_types'):
                    n = rng.choice([0, 1, 2, 300])
                    setattr(msg, name, [_mutate(type(item)(), rng, depth + 1) if rng.random() < 0.5
                                        else _mutate(fill(type(item)(), rng, 3), rng, depth + 1) for _ in range(n)])
            elif hasattr(value, 'get_fields_and_field_types') and depth < 4:
                _mutate(value, rng, depth + 1)
        except (AssertionError, TypeError, ValueError, OverflowError):
            pass                                   # the message type itself refuses the value
    return msg


def _hostile(msg_type, rng, good=None):
    """A hostile instance of ``msg_type``: a mutated good one, a random one, or an empty one."""
    r = rng.random()
    if good is not None and r < 0.5:
        msg = msg_type()
        for name in msg.get_fields_and_field_types():
            setattr(msg, name, getattr(good, name))
        import copy
        msg = copy.deepcopy(msg)
    elif r < 0.9:
        msg = fill(msg_type(), rng)
    else:
        return msg_type()
    return _mutate(msg, rng)


@pytest.fixture(scope='module')
def good_frames():
    return [frame_detections_to_msg(obs) for obs in detected_frames(frames=30)]


def _deliver(callback, msg, rng=None):
    """A subscription's callback as rclpy calls it: with the message info where it takes
    one (hostile too, with ``rng``: any stamp, any sequence number)."""
    try:
        inspect.signature(callback).bind(object())
    except TypeError:
        info = {'received_timestamp': time.time_ns(), 'publication_sequence_number': 1}
        if rng is not None:
            info = {'received_timestamp': rng.choice([0, 1, time.time_ns(), 2 ** 63 - 1]),
                    'publication_sequence_number': rng.choice([0, 1, 2 ** 40, 2 ** 64 - 1])}
        return callback(msg, info)
    return callback(msg)


def test_no_hostile_message_or_request_kills_a_node(tmp_path, good_frames):
    from rfm_detector_node.detector_node import DetectorNode
    from rfm_mapper_node.mapper_node import MapperNode
    from rfm_matcher_node.matcher_node import MatcherNode

    rng = random.Random(SEED)
    rclpy.init()
    nodes = []
    try:
        nodes = [DetectorNode(parameter_overrides=[Parameter('backend', value='depth_clusters')]),
                 MatcherNode(),
                 MapperNode(parameter_overrides=[Parameter('map_path', value=str(tmp_path / 'maps' / 'map.rfm'))])]
        detector, matcher, mapper = nodes
        callbacks = []
        for node in nodes:
            for sub in node.subscriptions:
                callbacks.append((node.get_name(), 'topic', sub.topic_name, sub.msg_type, sub.callback))
            for srv in node.services:
                if 'parameter' in srv.srv_name:     # rclpy's own (a bad Parameter.Type raises in rclpy)
                    continue
                callbacks.append((node.get_name(), 'service', srv.srv_name, srv.srv_type, srv.callback))
        assert len(callbacks) >= 12, [c[:3] for c in callbacks]
        good = {'/rfm/detections': good_frames[0]}
        hits = dict.fromkeys(c[2] for c in callbacks)
        for i in range(N):
            name, kind, topic, typ, callback = rng.choice(callbacks)
            hits[topic] = (hits[topic] or 0) + 1
            try:
                if kind == 'topic':
                    _deliver(callback, _hostile(typ, rng, good.get(topic)), rng)
                else:
                    request = _hostile(typ.Request, rng)
                    response = callback(request, typ.Response())
                    assert response is not None and hasattr(response, 'success') or not hasattr(typ.Response(),
                                                                                              'success')
            except Exception as exc:  # noqa: BLE001 - the point of the test
                pytest.fail(f'input {i}: {name} {kind} {topic} raised {exc!r}')
        assert all(hits.values()), hits                   # every input of every node was hit
        print(f'{N} hostile inputs: ' + ', '.join(f'{t} {n}' for t, n in sorted(hits.items())))
        deadline = time.monotonic() + 60
        while not detector.worker.idle and time.monotonic() < deadline:     # the frames it took, done
            time.sleep(0.05)
        for node in nodes:                                # the timers after hostile input
            for timer in node.timers:
                timer.callback()
        assert [node.unexpected_errors for node in nodes] == [0, 0, 0], mapper.core.session.message
        detector.worker.stop()
        # ... and each keeps serving good input, nothing reset: the matcher makes keyframes of
        # good frames, the mapper maps them
        from rfm_msgs.srv import SetMode
        set_mode = next(s for s in mapper.services if s.srv_name.endswith('/set_mode'))
        set_mode.callback(SetMode.Request(mode=0), SetMode.Response())
        before = matcher.graph.stats.keyframes
        kf_sub = next(s for s in mapper.subscriptions if s.topic_name == '/rfm/keyframes')
        published = []
        matcher.keyframe_pub.publish = published.append
        for msg in good_frames:
            _deliver(next(s for s in matcher.subscriptions if s.topic_name == '/rfm/detections').callback, msg)
        assert matcher.graph.stats.keyframes > before
        for msg in published:
            kf_sub.callback(msg)
        stamps = {f.stamp_ns for f in mapper.core.mapper.keyframes.values()}
        assert len(published) >= 2 and all(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec in stamps
                                           for m in published)
        for timer in mapper.timers:
            timer.callback()
        assert mapper.unexpected_errors == 0, mapper.core.session.message
        import numpy as np
        assert all(np.isfinite(p.yaw) and np.all(np.isfinite(p.t)) for p in mapper.core.mapper.poses.values())
    finally:
        for node in nodes:
            if isinstance(node, DetectorNode):
                node.worker.stop()
            node.destroy_node()
        rclpy.try_shutdown()


def test_an_unexpected_error_in_a_timer_is_counted_and_the_node_goes_on(tmp_path):
    """Every node's callbacks and timers run guarded alike: the error is counted (the
    matcher's and detector's /diagnostics, the mapper's rfm/status message), logged, and the
    next call runs as if nothing happened."""
    from rfm_mapper_node.mapper_node import MapperNode
    from rfm_matcher_node.matcher_node import MatcherNode

    rclpy.init()
    nodes = []
    try:
        mapper = MapperNode(parameter_overrides=[Parameter('map_path', value=str(tmp_path / 'map.rfm'))])
        matcher = MatcherNode()
        nodes = [mapper, matcher]
        tick = next(t for t in mapper.timers if t.callback.__name__ == '_tick')
        real = mapper.core.tick
        mapper.core.tick = lambda: 1 / 0
        tick.callback()
        assert mapper.unexpected_errors == 1 and 'ZeroDivisionError' in mapper.core.session.message
        mapper.core.tick = real
        tick.callback()
        assert mapper.unexpected_errors == 1
        diagnostics = next(t for t in matcher.timers if t.callback.__name__ == '_publish_diagnostics')
        published = []
        matcher.diag_pub.publish = published.append
        matcher.graph.stats = None                       # breaks the diagnostics once
        diagnostics.callback()
        assert matcher.unexpected_errors == 1 and not published
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
