"""
Start coreg_node with its parameter file: ``ros2 launch coreg_ros coreg.launch.py``.

Arguments: ``params_file:=PATH`` (default: the package's config/coreg.yaml, whose section is
``coreg_node``, the node's name) and ``log_level:=debug|info|warn|error``. The calibration
appears on ``/coreg_node/base_to_base``, ``/coreg_node/tool_to_marker`` and ``/tf_static``
(``publish_tf``; docs/tf.md).
"""

import os

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

#: The parameter file beside this launch file: config/ next to launch/, in the source tree and
#: in the installed share/coreg_ros alike (setup.py data_files), so no package lookup is needed.
DEFAULT_PARAMS = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, 'config',
                              'coreg.yaml')


def generate_launch_description():
    """Declare the arguments and the node."""
    return LaunchDescription([
        DeclareLaunchArgument(
            'params_file', default_value=os.path.normpath(DEFAULT_PARAMS),
            description='parameter file of coreg_node (section coreg_node: ros__parameters:)'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='debug, info, warn or error'),
        Node(package='coreg_ros', executable='coreg_node', name='coreg_node', output='screen',
             parameters=[LaunchConfiguration('params_file')],
             arguments=['--ros-args', '--log-level', LaunchConfiguration('log_level')]),
    ])
