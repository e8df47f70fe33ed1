"""The mapper killed with SIGKILL mid-run and restarted with load_map_on_start (#19 item 3):
the map continues from its last autosave with no id collision and a final map that
validates. While the matcher goes on, the restarted mapper gets what the autosave missed from
the matcher's kept history (nothing lost); a matcher restarted too loses at most
autosave_every_n_keyframes keyframes."""
import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')
from ament_index_python.packages import get_package_prefix  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'ros'))
from test_mapper_node import GRAPH_QOS, _graph_messages  # noqa: E402

from rfm_core.mapping.map_io import read_map  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
AUTOSAVE = 3


def _held(status) -> int:
    """Keyframes a mapper holds (its status): in its map, or culled into one of them."""
    return status.num_keyframes + status.num_culled


def _saved(content) -> int:
    """Keyframes a map file holds (``read_map``): in the map, or culled into one of them."""
    return len(content['keyframes']) + len(content['merged'])


def _mapper(map_path, load: bool):
    exe = os.path.join(get_package_prefix('rfm_mapper_node'), 'lib', 'rfm_mapper_node', 'mapper')
    return subprocess.Popen([exe, '--ros-args', '-p', f'map_path:={map_path}', '-p',
                             f'autosave_every_n_keyframes:={AUTOSAVE}', '-p', f'load_map_on_start:={str(load).lower()}'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _numbered(messages, session):
    """The messages numbered as the matcher node numbers them (its session, a sequence per type)."""
    numbers = {}
    for m in messages:
        m.session, m.sequence = session, next(numbers.setdefault(type(m), itertools.count(1)))
    return messages


def _renumbered(messages):
    """The messages as a matcher restarted at the crash would send them: keyframe ids from 0
    again, nothing that refers to a keyframe from before, a new session."""
    import copy

    from rfm_msgs.msg import Keyframe, ViewGraphEdge
    first = min(m.keyframe_id for m in messages if isinstance(m, Keyframe))
    out = []
    for m in map(copy.deepcopy, messages):
        if isinstance(m, ViewGraphEdge):
            if min(m.source_id, m.target_id) < first:
                continue
            m.source_id, m.target_id = m.source_id - first, m.target_id - first
        elif m.keyframe_id < first:
            continue
        else:
            m.keyframe_id -= first
        out.append(m)
    return _numbered(out, 2)


@pytest.mark.parametrize('matcher_restarts', [False, True], ids=['matcher-goes-on', 'matcher-restarts'])
def test_a_killed_mapper_continues_from_its_autosave(tmp_path, matcher_restarts):
    from rfm_msgs.msg import Keyframe, MapperStatus, TrackedFrame, ViewGraphEdge
    from rfm_msgs.srv import SaveMap

    messages, truth, _ = _graph_messages()
    messages = _numbered(messages, 1)
    keyframes = [m for m in messages if isinstance(m, Keyframe)]
    cut = messages.index(keyframes[len(keyframes) // 2 + 1])        # the crash comes after ~half
    map_path = tmp_path / 'map.rfm'
    rclpy.init()
    node = rclpy.create_node('crash_test')
    procs = []
    try:
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)

        def publishers():            # the matcher's (its keyframes and edges kept for late subscribers)
            return {Keyframe: node.create_publisher(Keyframe, 'rfm/keyframes', GRAPH_QOS),
                    ViewGraphEdge: node.create_publisher(ViewGraphEdge, 'rfm/view_graph/edges', GRAPH_QOS),
                    TrackedFrame: node.create_publisher(TrackedFrame, 'rfm/tracked_frames', reliable)}
        pubs = publishers()
        status = []
        node.create_subscription(MapperStatus, 'rfm/status', status.append, 10)

        def wait(predicate, timeout=60.0):
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline and not predicate():
                rclpy.spin_once(node, timeout_sec=0.1)
                for p in procs:
                    assert p.poll() is None or p.returncode == -signal.SIGKILL, p.stdout.read()
            return predicate()

        def feed(batch):
            assert wait(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()))
            for msg in batch:
                pubs[type(msg)].publish(msg)
                rclpy.spin_once(node, timeout_sec=0.005)

        procs.append(_mapper(map_path, load=False))
        first = messages[:cut]
        n_first = sum(isinstance(m, Keyframe) for m in first)
        feed(first)
        assert wait(lambda: status and _held(status[-1]) == n_first), status[-1:]
        assert wait(lambda: map_path.exists() and _saved(read_map(map_path)) >= n_first - AUTOSAVE)
        procs[0].send_signal(signal.SIGKILL)                      # no final save, no clean shutdown
        procs[0].wait(timeout=10)
        saved = read_map(map_path)                                # the autosave is whole (atomic writes)
        n_saved = _saved(saved)
        assert n_first - AUTOSAVE <= n_saved <= n_first

        status.clear()
        if matcher_restarts:                                      # its kept history goes with it
            for pub in pubs.values():
                node.destroy_publisher(pub)
            pubs = publishers()
        procs.append(_mapper(map_path, load=True))
        # the autosave, and (matcher going on) what it missed, from the matcher's history
        n_back = n_saved if matcher_restarts else n_first
        assert wait(lambda: status and _held(status[-1]) == n_back), status[-1:]
        rest = _renumbered(messages[cut:]) if matcher_restarts else messages[cut:]
        n_rest = sum(isinstance(m, Keyframe) for m in rest)
        feed(rest)
        assert wait(lambda: status and _held(status[-1]) == n_back + n_rest), status[-1:]
        client = node.create_client(SaveMap, 'rfm/save_map')
        assert client.wait_for_service(timeout_sec=20)
        future = client.call_async(SaveMap.Request(path=str(tmp_path / 'final.rfm')))
        assert wait(lambda: future.done()) and future.result().success, future.result()
        final = read_map(tmp_path / 'final.rfm')
        held = _saved(final)
        assert held == n_back + n_rest and len(truth) - held <= (AUTOSAVE if matcher_restarts else 0)
        stamps = [f.stamp_ns for f in final['keyframes'].values()] + [m.stamp_ns for m in final['merged'].values()]
        assert len(set(stamps)) == len(stamps)                    # no keyframe twice, none confused
        # the loaded map stays registered (keyframes after a lost one may form a component of
        # their own until relocalization joins them: #20)
        assert len(final['poses']) >= len(saved['poses']) >= 2
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    p.kill()
        node.destroy_node()
        rclpy.try_shutdown()
