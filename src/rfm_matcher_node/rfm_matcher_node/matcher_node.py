"""rfm matcher node: keyframes and a view graph of verified 4-DoF relative poses (paper 3.2-3.4).

Thin rclpy wrapper: the algorithms live in rfm_core (no ROS there).
"""
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


class MatcherNode(Node):

    def __init__(self):
        super().__init__('matcher')
        self.get_logger().info('matcher ready')


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = MatcherNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
