"""Second process of the interface round-trip test.

Republishes every message it receives on ``rfm_test/in/<Type>`` to ``rfm_test/out/<Type>``
and answers every service ``rfm_test/<Type>`` with ``msg_fill.response_for``. Exits cleanly
on SIGINT.
"""
import os
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from msg_fill import interface_types, response_for  # noqa: E402

QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


class EchoServer(Node):

    def __init__(self):
        super().__init__('rfm_interface_echo')
        msg_types, srv_types = interface_types()
        self._keep = []
        for msg_type in msg_types:
            pub = self.create_publisher(msg_type, f'rfm_test/out/{msg_type.__name__}', QOS)
            self._keep.append(self.create_subscription(
                msg_type, f'rfm_test/in/{msg_type.__name__}',
                lambda msg, pub=pub: pub.publish(msg), QOS))
        for srv_type in srv_types:
            self._keep.append(self.create_service(
                srv_type, f'rfm_test/{srv_type.__name__}',
                lambda request, response, srv_type=srv_type: response_for(srv_type, request)))
        self.get_logger().info('echo server ready')


def main():
    rclpy.init()
    node = EchoServer()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
