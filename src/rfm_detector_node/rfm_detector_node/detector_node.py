"""rfm detector node: per-frame metric 3D boxes and embeddings (paper section 3.1).

Thin rclpy wrapper: the algorithms live in rfm_core (no ROS there).
"""
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


class DetectorNode(Node):

    def __init__(self):
        super().__init__('detector')
        self.get_logger().info('detector ready')


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = DetectorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
