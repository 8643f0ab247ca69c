"""Start feature_node, matcher_node and mapping_node with the shipped parameter files.

    ros2 launch semfeat_ros semfeat.launch.py [image_topic:=...] [camera_info_topic:=...]
        [input_transport:=raw|compressed] [use_sim_time:=true] [config_dir:=DIR]

Every input and output topic can also be remapped per node with the usual --ros-args rules.
"""
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

NODES = ('feature_node', 'matcher_node', 'mapping_node')


def generate_launch_description() -> LaunchDescription:
    args = [
        DeclareLaunchArgument('image_topic', default_value='/camera/front/image_raw',
                              description='Front camera images (raw; +/compressed)'),
        DeclareLaunchArgument('camera_info_topic', default_value='/camera/front/camera_info',
                              description='CameraInfo of the front camera'),
        DeclareLaunchArgument('odom_topic', default_value='/vehicle/odom',
                              description='Wheel odometry (nav_msgs/Odometry)'),
        DeclareLaunchArgument('gnss_topic', default_value='/gnss/fix',
                              description='GNSS fixes (sensor_msgs/NavSatFix)'),
        DeclareLaunchArgument('input_transport', default_value='raw',
                              description='raw or compressed camera input'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='Use /clock (bag replay)'),
        DeclareLaunchArgument('config_dir',
                              default_value=PathJoinSubstitution(
                                  [FindPackageShare('semfeat_ros'), 'config']),
                              description='Directory with <node>.yaml parameter files'),
    ]
    remap = [
        ('/camera/front/image_raw', LaunchConfiguration('image_topic')),
        ('/camera/front/image_raw/compressed',
         [LaunchConfiguration('image_topic'), '/compressed']),
        ('/camera/front/camera_info', LaunchConfiguration('camera_info_topic')),
        ('/vehicle/odom', LaunchConfiguration('odom_topic')),
        ('/gnss/fix', LaunchConfiguration('gnss_topic')),
    ]
    nodes = []
    for name in NODES:
        params = [PathJoinSubstitution([LaunchConfiguration('config_dir'), f'{name}.yaml']),
                  {'use_sim_time': LaunchConfiguration('use_sim_time')}]
        if name in ('feature_node', 'matcher_node'):
            params.append({'input_transport': LaunchConfiguration('input_transport')})
        nodes.append(Node(package='semfeat_ros', executable=name, name=name, output='screen',
                          parameters=params, remappings=remap))
    return LaunchDescription(args + nodes)
