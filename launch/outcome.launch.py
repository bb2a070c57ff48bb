"""Start outcome_node with config/outcome_node.yaml.

    ros2 launch task_outcome_ros outcome.launch.py [namespace:=cam1]
        [depth_topic:=/camera/depth/image_raw] [camera_info_topic:=/camera/depth/camera_info]
        [params_file:=/path/to/my.yaml]

For 640x480 depth over DDS on one host, also export
FASTRTPS_DEFAULT_PROFILES_FILE=<share>/task_outcome_ros/config/fastdds_shm.xml in every process
(publisher too) so whole frames travel over shared memory instead of fragmented UDP.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory("task_outcome_ros"), "config",
                                  "outcome_node.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="",
                              description="Namespace of the node and its relative topics."),
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="Parameter YAML (outcome_node: ros__parameters:)."),
        DeclareLaunchArgument("depth_topic", default_value="depth/image_raw",
                              description="Depth image topic (32FC1 m or 16UC1 mm)."),
        DeclareLaunchArgument("camera_info_topic", default_value="depth/camera_info",
                              description="CameraInfo of the depth image (for 3-D centroids)."),
        Node(
            package="task_outcome_ros",
            executable="outcome_node",
            name="outcome_node",
            namespace=LaunchConfiguration("namespace"),
            parameters=[LaunchConfiguration("params_file")],
            remappings=[("depth/image_raw", LaunchConfiguration("depth_topic")),
                        ("depth/camera_info", LaunchConfiguration("camera_info_topic"))],
            output="screen",
            emulate_tty=True,
        ),
    ])
