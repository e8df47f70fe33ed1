"""rfm_core: the ROS-free core of rfm, an implementation of Rooms from Motion.

Modules map to the paper's stages: ``geometry`` (boxes, 4-DoF poses, IoU, Kabsch),
``observations`` (data types between stages), ``io`` (images, sync, messages).
Nothing here imports rclpy.
"""

__version__ = '0.1.0'
