"""The topic names of a RealSense-style RGB-D camera with an IMU (realsense2_camera with
align_depth, and rfm's simulated bags), and of the simulator's ground truth: one table for
the simulator, the bag readers, ``rfm run``'s default remaps and the launch file."""
from __future__ import annotations

__all__ = ['CAMERA_TOPICS', 'GROUND_TRUTH_TOPICS', 'OPTICAL_FRAME']

OPTICAL_FRAME = 'camera_color_optical_frame'    #: the colour camera's optical frame (realsense2_camera's name)

CAMERA_TOPICS = {
    'color': '/camera/color/image_raw',
    'color_info': '/camera/color/camera_info',
    'depth': '/camera/depth/image_raw',          # registered to colour
    'depth_info': '/camera/depth/camera_info',
    'imu': '/imu/data',
    'tf_static': '/tf_static',
    'odom': '/odom',                             # a robot's wheel odometry (and odom -> base_link on /tf)
    'tf': '/tf',
}
GROUND_TRUTH_TOPICS = {
    'gt_pose': '/ground_truth/camera_pose',
    'gt_objects': '/ground_truth/objects',
    'gt_detections': '/ground_truth/detections',
}
