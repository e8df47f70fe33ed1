"""The node packages install `ros2 run`-style executables that start real nodes."""
import os
import signal
import subprocess
import time

import pytest

rclpy = pytest.importorskip('rclpy')
from ament_index_python.packages import get_package_prefix  # noqa: E402

pytestmark = pytest.mark.ros

EXECUTABLES = [('rfm_detector_node', 'detector', 'detector'),
               ('rfm_matcher_node', 'matcher', 'matcher'),
               ('rfm_mapper_node', 'mapper', 'mapper')]
#: a topic each node publishes once its constructor is done (models loaded, services created)
READY_TOPIC = {'detector': '/rfm/detections', 'matcher': '/rfm/tracked_frames', 'mapper': '/rfm/status'}


def executable(package, name):
    path = os.path.join(get_package_prefix(package), 'lib', package, name)
    assert os.access(path, os.X_OK), f'{path} is not an executable'
    return path


def stop(proc, timeout=15):
    """Output of a process told to stop; killed (never leaked) if it does not."""
    try:
        return proc.communicate(timeout=timeout)[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()[0] + '\n[killed: did not stop on SIGINT]'


@pytest.mark.slow
def test_nodes_start_join_the_graph_and_stop_on_sigint():
    procs = [subprocess.Popen([executable(pkg, exe)], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
             for pkg, exe, _ in EXECUTABLES]
    rclpy.init()
    observer = rclpy.create_node('rfm_graph_observer')
    try:
        wanted = {node for _, _, node in EXECUTABLES}
        deadline = time.monotonic() + 30
        ready = set()
        while time.monotonic() < deadline and ready != wanted:
            rclpy.spin_once(observer, timeout_sec=0.2)
            for p in procs:
                assert p.poll() is None, p.stdout.read()
            # A node is fully up once its output topic is advertised (its constructor is done:
            # a SIGINT while it still imports torch would abort the process, not test the node)
            for name in wanted - ready:
                if name in observer.get_node_names():
                    topics = observer.get_publisher_names_and_types_by_node(name, '/')
                    if any(t == READY_TOPIC[name] for t, _ in topics):
                        ready.add(name)
        assert ready == wanted, f'nodes not up: {wanted - ready}'
        # a node that seems hung tells where, and goes on: SIGUSR1 writes its threads' stacks
        mapper = procs[-1]
        mapper.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        assert mapper.poll() is None
    finally:
        observer.destroy_node()
        rclpy.try_shutdown()
        for p in procs:
            p.send_signal(signal.SIGINT)
        outputs = [stop(p) for p in procs]
    for p, out in zip(procs, outputs):
        assert p.returncode == 0, out
    assert 'most recent call first' in outputs[-1] and 'spin_once' in outputs[-1], outputs[-1][-2000:]


def test_a_signal_while_a_node_is_built_stops_it_once_built_and_sigterm_stops_a_spinning_one():
    """Ctrl-C that lands inside a node's constructor (its models loading) does not fail the
    build on a shut-down context: the node is built, closed and destroyed, and run_node
    returns. SIGTERM (kill, docker stop) stops a spinning node the same way, between callbacks."""
    import rclpy.executors  # noqa: F401 - run_node spins one
    from rclpy.node import Node
    from std_msgs.msg import Empty

    from rfm_core.io.entry import run_node

    built, closed, ticks = [], [], []

    def interrupted_build():
        node = Node('rfm_entry_test')
        os.kill(os.getpid(), signal.SIGINT)                         # Ctrl-C mid-build
        node.create_publisher(Empty, 'rfm_entry_test', 1)          # ... which goes on
        built.append(node)
        return node

    def tick():
        ticks.append(time.monotonic())
        if len(ticks) == 3:
            os.kill(os.getpid(), signal.SIGTERM)

    def ticking():
        node = Node('rfm_entry_test')
        node.create_timer(0.05, tick)
        built.append(node)
        return node

    handler = signal.getsignal(signal.SIGINT)
    for make in (interrupted_build, ticking):
        run_node(rclpy, make, 'test', close=closed.append)
        assert closed == built and not rclpy.ok()
    assert len(built) == 2 and len(ticks) == 3                   # the spinning one stopped after its third tick
    assert signal.getsignal(signal.SIGINT) is handler
