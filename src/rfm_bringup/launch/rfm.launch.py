"""Launch the rfm graph (detector -> matcher -> mapper) with a full ROS 2 install.

    ros2 launch rfm_bringup rfm.launch.py                      # RealSense-style topics
    ros2 launch rfm_bringup rfm.launch.py use_sim_time:=true   # with `rfm play BAG` / `ros2 bag play --clock`
    ros2 launch rfm_bringup rfm.launch.py color:=/cam/image depth:=/cam/depth camera_info:=/cam/info imu:=/cam/imu

The same nodes as `rfm run` (which needs no launch system). The arguments that set node
parameters take their defaults and descriptions from the nodes' settings (rfm_core.config);
an empty map_path is the mapper's own default, $ROS_HOME/rfm/map.rfm.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from rfm_core.config import NODES, launch_arguments
from rfm_core.io.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS

OTHER = {
    'color': (CAMERA_TOPICS['color'], 'colour image topic (rgb8 / bgr8 / mono8)'),
    'camera_info': (CAMERA_TOPICS['color_info'], 'camera_info of the colour image'),
    'depth': (CAMERA_TOPICS['depth'], 'depth registered to colour (16UC1 mm or 32FC1 m)'),
    'imu': (CAMERA_TOPICS['imu'], 'IMU (gravity from the accelerometer, gyro-aided)'),
    'use_sim_time': ('false', 'true when replaying a bag with /clock'),
}


def generate_launch_description():
    arguments = launch_arguments()
    declared = [DeclareLaunchArgument(name, default_value=default, description=text)
                for name, (default, text) in OTHER.items()]
    declared += [DeclareLaunchArgument(name, default_value=default, description=text)
                 for name, default, text, _, _ in arguments]
    params = {node: {'use_sim_time': LaunchConfiguration('use_sim_time')} for node in NODES}
    for name, _, _, targets, is_text in arguments:
        for node, parameter in targets:
            value = LaunchConfiguration(name)
            params[node][parameter] = ParameterValue(value, value_type=str) if is_text else value
    topic = LaunchConfiguration
    remaps = [('rgb/image', topic('color')), ('rgb/camera_info', topic('camera_info')), ('depth/image', topic('depth')),
              ('imu', topic('imu')), ('ground_truth/detections', GROUND_TRUTH_TOPICS['gt_detections'])]
    nodes = [Node(package=f'rfm_{node}_node', executable=node, name=node, output='screen', parameters=[params[node]],
                  remappings=remaps if node == 'detector' else []) for node in NODES]
    return LaunchDescription(declared + nodes)
