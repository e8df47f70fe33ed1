"""Subscriptions taken in batches (rfm_detector_node.polling): no executor runs them, and
take_all hands over every queued message in order."""
import threading
import time

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

pytestmark = pytest.mark.ros


def test_a_polled_subscription_queues_until_taken_and_keeps_the_order():
    from sensor_msgs.msg import Imu

    from rfm_detector_node.polling import PolledGroup, take_all

    rclpy.init()
    try:
        node, pub_node = Node('polled_test'), Node('polled_test_pub')
        called, taken = [], []
        sub = node.create_subscription(Imu, 'polled_imu', called.append,
                                       QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
                                       callback_group=PolledGroup())
        pub = pub_node.create_publisher(Imu, 'polled_imu', QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        thread = threading.Thread(target=executor.spin, daemon=True)
        thread.start()
        deadline = time.monotonic() + 10
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        for i in range(50):
            msg = Imu()
            msg.header.stamp.nanosec = i
            pub.publish(msg)
        deadline = time.monotonic() + 10
        while len(taken) < 50 and time.monotonic() < deadline:
            time.sleep(0.1)
            take_all(sub, taken.append)
        assert called == []                           # the spinning executor never ran it
        assert [m.header.stamp.nanosec for m in taken] == list(range(50))
        assert take_all(sub, taken.append) == 0       # nothing left
        executor.shutdown()
        thread.join(timeout=5)
        node.destroy_node()
        sub_destroyed = take_all(sub, taken.append)   # a destroyed subscription: nothing, no error
        assert sub_destroyed == 0
        pub_node.destroy_node()
    finally:
        rclpy.try_shutdown()
