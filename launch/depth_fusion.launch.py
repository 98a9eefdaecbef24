"""Launch the depth_fusion node graph (needs a full ROS 2 install with ``launch`` and ``launch_ros``).

    ros2 launch depth_fusion_ros depth_fusion.launch.py
    ros2 launch depth_fusion_ros depth_fusion.launch.py bag:=/data/room.mcap use_sim_time:=true
    ros2 launch depth_fusion_ros depth_fusion.launch.py image:=/camera/color/image_raw \\
        camera_info:=/camera/color/camera_info pose:=/orb_slam3/camera_pose \\
        corrected_path:=/orb_slam3/trajectory
    ros2 launch depth_fusion_ros depth_fusion.launch.py map:=true    # + map_node (TSDF map)

Starts ``multi_view_node``, ``single_view_node`` and ``fusion_node`` with one parameter file
(``params_file``, default: the installed ``config/depth_fusion.yaml``) and, when ``bag`` is
given, ``bag_replayer`` playing it (with ``/clock`` when ``use_sim_time`` is true), and with
``map:=true`` ``map_node``, which integrates the fused depth into a TSDF map (``ros2 service
call /map_node/save_map std_srvs/srv/Trigger`` writes its mesh; docs/mapping.md). The input
topics of the multi-view node are remapped from the launch arguments; the outputs stay under
``/depth_fusion``. Without a ROS install, ``depth-fusion run`` does the same in one command.
"""

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

from launch import LaunchDescription

PACKAGE = 'depth_fusion_ros'


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory(PACKAGE), 'config', 'depth_fusion.yaml')
    params_file = LaunchConfiguration('params_file')
    use_sim_time = LaunchConfiguration('use_sim_time')
    bag = LaunchConfiguration('bag')
    common = [params_file, {'use_sim_time': use_sim_time}]

    arguments = [
        DeclareLaunchArgument(
            'params_file', default_value=default_params, description='node parameters (YAML)'
        ),
        DeclareLaunchArgument(
            'use_sim_time', default_value='false', description='use /clock (true when playing a bag)'
        ),
        DeclareLaunchArgument(
            'bag', default_value='', description='rosbag2 to play with bag_replayer (optional)'
        ),
        DeclareLaunchArgument(
            'map', default_value='false', description='also start map_node (TSDF map of the fused depth)'
        ),
        DeclareLaunchArgument(
            'image', default_value='/camera/rgb/image_color', description='colour image topic'
        ),
        DeclareLaunchArgument(
            'camera_info', default_value='/camera/rgb/camera_info', description='camera_info of the image'
        ),
        DeclareLaunchArgument(
            'pose',
            default_value='/camera/pose',
            description='PoseStamped camera-to-world from SLAM or the bag',
        ),
        DeclareLaunchArgument(
            'corrected_path',
            default_value='/camera/corrected_path',
            description="nav_msgs/Path: the SLAM's corrected trajectory after a loop closure (optional)",
        ),
    ]
    corrected_path = ('camera/corrected_path', LaunchConfiguration('corrected_path'))
    multi_view = Node(
        package=PACKAGE,
        executable='multi_view_node',
        name='multi_view_node',
        output='screen',
        parameters=common,
        remappings=[
            ('camera/rgb/image_color', LaunchConfiguration('image')),
            ('camera/rgb/camera_info', LaunchConfiguration('camera_info')),
            ('camera/pose', LaunchConfiguration('pose')),
            corrected_path,
        ],
    )
    single_view = Node(
        package=PACKAGE,
        executable='single_view_node',
        name='single_view_node',
        output='screen',
        parameters=common,
    )
    fusion = Node(
        package=PACKAGE, executable='fusion_node', name='fusion_node', output='screen', parameters=common
    )
    mapping = Node(
        package=PACKAGE,
        executable='map_node',
        name='map_node',
        output='screen',
        parameters=common,
        remappings=[corrected_path],
        condition=IfCondition(LaunchConfiguration('map')),
    )
    replayer = Node(
        package=PACKAGE,
        executable='bag_replayer',
        name='bag_replayer',
        output='screen',
        parameters=[
            params_file,
            {
                'bag': bag,
                'publish_clock': use_sim_time,
                'use_sim_time': False,
                # play only once every node said it is ready (its /depth_fusion/ready line),
                # so the first frames are not lost
                'wait_ready': ['multi_view_node', 'single_view_node', 'fusion_node'],
                # and up to 60 s for fusion_node's kernels (compiled in the background) to be
                # built, so the replay meets the graph at full speed (as depth-fusion run does)
                'wait_warm': 60.0,
            },
        ],
        condition=IfCondition(PythonExpression(["'", bag, "' != ''"])),
    )
    return LaunchDescription([*arguments, multi_view, single_view, fusion, mapping, replayer])
