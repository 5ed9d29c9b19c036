"""The driver shim and the FDI nodes on a robot (apt ROS 2 Jazzy):

    ros2 launch youbot_fdi youbot_fdi.launch.py [composed:=true|false] [fused:=false|true]
        [params_file:=PARAMS.yaml] [can_interface:=socketcan] [can_channel:=can0]
        [aggregator:=true|false] [react:=false|true] [incident_dir:=DIR]

``composed:=true`` (default) runs kinematics_bridge, observer, residual_generator and decision in
one process (``youbot_fdi_suite``: a weak robot PC); ``false`` runs them as separate processes.
``fused:=true`` (with ``composed:=true``) runs ``youbot_fdi_fused`` instead: the observer computes
the residuals itself (the weakest PCs). ``params_file`` is a ``youbot-fdi identify`` output for
the observer, residual generator and decision. ``aggregator:=true`` starts
diagnostic_aggregator with config/diagnostic_aggregator.yaml (rqt_robot_monitor shows one tree).
``react:=true`` lets the kinematics bridge apply the fault reactions of config/reactions.yaml.
The decision node keeps an incident recording for every alarm episode (config/incidents.yaml) in
``incident_dir`` (default: $ROS_HOME/youbot_fdi/incidents).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

PACKAGE = 'youbot_fdi'


def config(name):
    return os.path.join(get_package_share_directory(PACKAGE), 'config', name)


def generate_launch_description():
    composed, fused = LaunchConfiguration('composed'), LaunchConfiguration('fused')
    fdi_parameters = [config('fdi.yaml'), config('incidents.yaml'),
                      {'params_file': LaunchConfiguration('params_file'),
                       'incident_dir': LaunchConfiguration('incident_dir')}]
    bridge_parameters = [config('kinematics_bridge.yaml'), config('reactions.yaml'),
                         {'react': LaunchConfiguration('react')}]
    separate = UnlessCondition(composed)

    def one_process(want_fused):
        return IfCondition(PythonExpression(["'", composed, "' == 'true' and ('", fused,
                                             "' == 'true') == ", str(want_fused)]))
    return LaunchDescription([
        DeclareLaunchArgument('composed', default_value='true',
                              description='FDI nodes in one process (true) or separate (false)'),
        DeclareLaunchArgument('fused', default_value='false',
                              description='with composed: the observer computes the residuals'),
        DeclareLaunchArgument('params_file', default_value='',
                              description='parameter file from youbot-fdi identify'),
        DeclareLaunchArgument('incident_dir', default_value='',
                              description="folder of the incident recordings ('' = "
                                          "$ROS_HOME/youbot_fdi/incidents)"),
        DeclareLaunchArgument('can_interface', default_value='socketcan'),
        DeclareLaunchArgument('can_channel', default_value='can0'),
        DeclareLaunchArgument('aggregator', default_value='false',
                              description='start diagnostic_aggregator with our analyzers'),
        DeclareLaunchArgument('react', default_value='false',
                              description='apply the fault reactions (config/reactions.yaml)'),
        Node(package=PACKAGE, executable='driver_shim', name='driver_shim', output='screen',
             parameters=[config('driver_shim.yaml'),
                         {'can_interface': LaunchConfiguration('can_interface'),
                          'can_channel': LaunchConfiguration('can_channel')}]),
        Node(package=PACKAGE, executable='youbot_fdi_suite', output='screen',
             parameters=bridge_parameters + fdi_parameters, condition=one_process(False)),
        Node(package=PACKAGE, executable='youbot_fdi_fused', output='screen',
             parameters=bridge_parameters + fdi_parameters, condition=one_process(True)),
        Node(package=PACKAGE, executable='kinematics_bridge', name='kinematics_bridge',
             output='screen', parameters=bridge_parameters, condition=separate),
        Node(package=PACKAGE, executable='observer', name='observer', output='screen',
             parameters=fdi_parameters, condition=separate),
        Node(package=PACKAGE, executable='residual_generator', name='residual_generator',
             output='screen', parameters=fdi_parameters, condition=separate),
        Node(package=PACKAGE, executable='decision', name='decision', output='screen',
             parameters=fdi_parameters, condition=separate),
        Node(package='diagnostic_aggregator', executable='aggregator_node', output='screen',
             parameters=[config('diagnostic_aggregator.yaml')],
             condition=IfCondition(LaunchConfiguration('aggregator'))),
    ])
