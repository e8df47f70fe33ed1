"""Every rfm_msgs message and service round-trips between two real rclpy processes."""
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from msg_fill import fill, interface_types, response_for  # noqa: E402

pytestmark = pytest.mark.ros
SRC = Path(__file__).resolve().parents[2] / 'src'


def test_every_interface_file_is_covered():
    msg_types, srv_types = interface_types()
    names = {t.__name__ for t in msg_types} | {t.__name__ for t in srv_types}
    on_disk = {p.stem for p in (SRC / 'rfm_msgs').glob('*/*.*') if p.suffix in ('.msg', '.srv')}
    assert on_disk <= names
    assert 'TFMessage' in names
    assert {'ObjectDetection', 'FrameDetections', 'Keyframe', 'ViewGraphEdge', 'MapObject',
            'ObjectMap', 'MapperStatus', 'Relocalize', 'SaveMap', 'LoadMap', 'SetMode'} <= names


@pytest.fixture(scope='module')
def echo_process():
    proc = subprocess.Popen([sys.executable, str(Path(__file__).parent / 'echo_server.py')],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    yield proc
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    assert proc.returncode == 0, out


@pytest.fixture(scope='module')
def node():
    rclpy.init()
    node = Node('rfm_interface_client')
    yield node
    node.destroy_node()
    rclpy.try_shutdown()


def spin_until(node, predicate, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return predicate()


def test_messages_and_services_round_trip(echo_process, node):
    assert os.environ['ROS_DOMAIN_ID'].isdigit()
    msg_types, srv_types = interface_types()
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    rng = random.Random(7)
    sent, received, pubs = {}, {}, {}
    for msg_type in msg_types:
        name = msg_type.__name__
        sent[name] = fill(msg_type(), rng)
        pubs[name] = node.create_publisher(msg_type, f'rfm_test/in/{name}', qos)
        node.create_subscription(msg_type, f'rfm_test/out/{name}',
                                 lambda msg, name=name: received.__setitem__(name, msg), qos)

    # Publish until each echo arrives (the first messages may precede discovery).
    deadline = time.monotonic() + 60
    while len(received) < len(sent) and time.monotonic() < deadline:
        assert echo_process.poll() is None, echo_process.stdout.read()
        for name, msg in sent.items():
            if name not in received:
                pubs[name].publish(msg)
        spin_until(node, lambda: len(received) == len(sent), 0.3)
    assert set(received) == set(sent), f'no echo for {set(sent) - set(received)}'
    for name, msg in sent.items():
        assert received[name] == msg, f'{name} changed on the way: {received[name]} != {msg}'

    for srv_type in srv_types:
        client = node.create_client(srv_type, f'rfm_test/{srv_type.__name__}')
        assert client.wait_for_service(timeout_sec=30), f'{srv_type.__name__} not offered'
        request = fill(srv_type.Request(), rng)
        future = client.call_async(request)
        assert spin_until(node, future.done, 30), f'{srv_type.__name__} call timed out'
        response = future.result()
        assert response == response_for(srv_type, request)
        assert response != srv_type.Response()    # non-trivial
