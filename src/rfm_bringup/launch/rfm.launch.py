"""Launch the rfm graph (detector -> matcher -> mapper) with a full ROS 2 install.

    ros2 launch rfm_bringup rfm.launch.py                      # RealSense-style topics
    ros2 launch rfm_bringup rfm.launch.py use_sim_time:=true   # with `rfm play BAG` / `ros2 bag play --clock`
    ros2 launch rfm_bringup rfm.launch.py color:=/cam/image depth:=/cam/depth camera_info:=/cam/info imu:=/cam/imu

The same nodes and defaults as `rfm run` (which needs no launch system).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from rfm_core.io.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS

ARGS = {
    'color': (CAMERA_TOPICS['color'], 'colour image topic (rgb8 / bgr8 / mono8)'),
    'camera_info': (CAMERA_TOPICS['color_info'], 'camera_info of the colour image'),
    'depth': (CAMERA_TOPICS['depth'], 'depth registered to colour (16UC1 mm or 32FC1 m)'),
    'imu': (CAMERA_TOPICS['imu'], 'IMU (gravity from the accelerometer, gyro-aided)'),
    'backend': ('depth_clusters', 'detector: depth_clusters | cutr | ground_truth'),
    'cutr_checkpoint': ('', 'cutr: path to cutr_rgb.pth / cutr_rgbd.pth'),
    'matcher': ('learned', 'object matcher: learned | classical'),
    'map_path': ('~/.ros/rfm/map.rfm', 'map file for save/load/autosave'),
    'mode': ('mapping', 'mapping | localization'),
    'load_map_on_start': ('false', 'load map_path at start-up'),
    'use_sim_time': ('false', 'true when replaying a bag with /clock'),
}


def generate_launch_description():
    cfg = {name: LaunchConfiguration(name) for name in ARGS}
    sim = {'use_sim_time': cfg['use_sim_time']}
    return LaunchDescription([
        *[DeclareLaunchArgument(name, default_value=default, description=text)
          for name, (default, text) in ARGS.items()],
        Node(package='rfm_detector_node', executable='detector', name='detector', output='screen',
             parameters=[{'backend': cfg['backend'], 'cutr.checkpoint': cfg['cutr_checkpoint'], **sim}],
             remappings=[('rgb/image', cfg['color']), ('rgb/camera_info', cfg['camera_info']),
                         ('depth/image', cfg['depth']), ('imu', cfg['imu']),
                         ('ground_truth/detections', GROUND_TRUTH_TOPICS['gt_detections'])]),
        Node(package='rfm_matcher_node', executable='matcher', name='matcher', output='screen',
             parameters=[{'matcher': cfg['matcher'], **sim}]),
        Node(package='rfm_mapper_node', executable='mapper', name='mapper', output='screen',
             parameters=[{'map_path': cfg['map_path'], 'mode': cfg['mode'], 'matcher': cfg['matcher'],
                          'load_map_on_start': cfg['load_map_on_start'], **sim}]),
    ])
