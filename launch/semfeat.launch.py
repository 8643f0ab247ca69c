"""Start feature_node, matcher_node and mapping_node (and RViz) with the shipped parameter files.

    ros2 launch semfeat_ros semfeat.launch.py [namespace:=car1] [use_sim_time:=true]
        [image_topic:=...] [camera_info_topic:=...] [odom_topic:=...] [gnss_topic:=...]
        [input_transport:=raw|compressed] [input_reliability:=best_effort|reliable]
        [camera_config:=FILE] [output_dir:=DIR] [rviz:=true] [managed:=true]
        [frontend:=semfeat|xfeat|sift|orb] [matcher:=mnn|learned] [config_dir:=DIR]

The nodes' topics are relative names: under ``namespace`` every input and output moves with it
(``/car1/camera/front/image_raw`` ... ``/car1/semantic_cloud``); /tf, /tf_static and
/diagnostics stay global. A topic argument that starts with ``/`` is taken as it is.

``managed:=true`` starts the managed (lifecycle) variants (``<node>_managed``) under the same
names and parameters instead: they start unconfigured, and a lifecycle manager or
``ros2 lifecycle set /<namespace>/<node> configure`` (then ``activate``) brings them up.
"""
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

NODES = ('feature_node', 'matcher_node', 'mapping_node')
# parameters of each node set from launch arguments of the same name
NODE_ARGS = {
    'feature_node': ('image_topic', 'camera_info_topic', 'input_transport',
                     'input_reliability', 'frontend'),
    'matcher_node': ('image_topic', 'camera_info_topic', 'input_transport', 'frontend',
                     'matcher'),
    'mapping_node': ('camera_info_topic', 'odom_topic', 'gnss_topic', 'input_reliability',
                     'camera_config', 'output_dir'),
}
ARGS = (
    ('namespace', '', 'Namespace of the nodes and their topics'),
    ('use_sim_time', 'false', 'Use /clock (bag replay)'),
    ('image_topic', 'camera/front/image_raw', 'Front camera images (raw; +/compressed)'),
    ('camera_info_topic', 'camera/front/camera_info', 'CameraInfo of the front camera'),
    ('odom_topic', 'vehicle/odom', 'Wheel odometry (nav_msgs/Odometry)'),
    ('gnss_topic', 'gnss/fix', 'GNSS fixes (sensor_msgs/NavSatFix)'),
    ('input_transport', 'raw', 'raw or compressed camera input'),
    ('input_reliability', 'best_effort', 'QoS reliability of the sensor inputs: best_effort '
     '(matches any publisher) or reliable (bag replay without drops at the source)'),
    ('camera_config', '', 'Calibration YAML with the base_link -> camera extrinsic, used when '
     '/tf_static does not carry it; empty = the shipped config/camera_front.yaml'),
    ('output_dir', 'semfeat_map', 'Where ~/save_map writes the map'),
    ('frontend', 'semfeat', 'Keypoints and descriptors of feature_node (semfeat, xfeat, sift, '
     "orb; labelled by the network's segmentation), told to matcher_node too"),
    ('matcher', 'mnn', 'matcher_node: mnn (mutual nearest neighbour) or learned (LighterGlue, '
     'frontend xfeat only)'),
    ('rviz', 'false', 'Start RViz2 with rviz/semfeat.rviz'),
    ('managed', 'false', 'Start the managed (lifecycle) variants <node>_managed, unconfigured, '
     'instead of the plain nodes'),
)


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare('semfeat_ros')
    args = [DeclareLaunchArgument(name, default_value=default, description=text)
            for name, default, text in ARGS]
    args.append(DeclareLaunchArgument(
        'config_dir', default_value=PathJoinSubstitution([share, 'config']),
        description='Directory with <node>.yaml parameter files'))
    nodes = []
    for name in NODES:
        params = [PathJoinSubstitution([LaunchConfiguration('config_dir'), f'{name}.yaml']),
                  {'use_sim_time': LaunchConfiguration('use_sim_time')},
                  {arg: ParameterValue(LaunchConfiguration(arg), value_type=str)
                   for arg in NODE_ARGS[name]}]  # strings as given ('' included)
        for executable, condition in ((name, UnlessCondition), (f'{name}_managed', IfCondition)):
            nodes.append(Node(package='semfeat_ros', executable=executable, name=name,
                              output='screen', namespace=LaunchConfiguration('namespace'),
                              parameters=params,
                              condition=condition(LaunchConfiguration('managed'))))
    nodes.append(Node(package='rviz2', executable='rviz2', name='rviz2', output='screen',
                      namespace=LaunchConfiguration('namespace'),
                      arguments=['-d', PathJoinSubstitution([share, 'rviz', 'semfeat.rviz'])],
                      parameters=[{'use_sim_time': LaunchConfiguration('use_sim_time')}],
                      condition=IfCondition(LaunchConfiguration('rviz'))))
    return LaunchDescription(args + nodes)
