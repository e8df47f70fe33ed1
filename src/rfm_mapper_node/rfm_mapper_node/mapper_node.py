"""rfm mapper node: pose averaging, object tracks, relocalization, map persistence (paper 3.5-3.6).

Thin rclpy wrapper: the algorithms live in rfm_core (no ROS there).
"""
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


class MapperNode(Node):

    def __init__(self):
        super().__init__('mapper')
        self.get_logger().info('mapper ready')


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = MapperNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
