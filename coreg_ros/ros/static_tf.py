"""
The calibration on ``/tf_static``, where the rest of a ROS system reads transforms.

Direction, tf2's (``header.frame_id`` the parent, ``child_frame_id`` the child, the transform
the child's pose in the parent, so a point p of the child is ``R p + t`` in the parent):

- T0, ``base_to_base``: parent ``frame_base_b`` -> child ``frame_base_a`` (A's base in B's);
- T1, ``tool_to_marker``: parent ``frame_tool`` -> child ``frame_marker`` (B's marker in A's
  tool).

Both go in one ``tf2_msgs/TFMessage``, latched as tf2's static broadcaster latches (reliable,
transient local, depth 1), stamped with the calibration time, after each published
calibration and at start-up for a stored result. T1's rotation of a position-only or
three-marker model is not estimated: identity, the marker frame's axes taken as the tool's.

The type: tf2_ros's ``StaticTransformBroadcaster`` where it is importable (a ROS install);
else ``tf2_msgs/msg/TFMessage`` with the same QoS (``make venv`` builds tf2_msgs from Jazzy's
definitions, with Jazzy's type hash: interfaces/build.sh); without either the node says so
once and publishes its own topics as before. docs/tf.md has the details.
"""

from __future__ import annotations

from coreg_ros.core.types import UncertainPose
from coreg_ros.files.export import frame_problem
from coreg_ros.ros.messages import pose_to_transform
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

TOPIC = '/tf_static'
#: tf2_ros StaticTransformBroadcaster's QoS: a late listener gets the last message.
STATIC_TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: What to do when no TFMessage type can be had (logged once at start-up).
MISSING_TYPE = (
    'publish_tf: neither tf2_ros nor tf2_msgs can be imported ({error}), so the calibration is '
    'not broadcast on /tf_static; ~/base_to_base and ~/tool_to_marker still carry it. Fix: '
    '`make venv` (builds tf2_msgs into the venv), or with ROS installed: apt install '
    'ros-jazzy-tf2-ros-py; publish_tf:=false silences this')


class StaticTf:
    """
    Broadcast T0 and T1 on /tf_static (see the module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
        The node the publisher belongs to.
    frames : dict
        ``{"base_a", "base_b", "tool", "marker"}``: the frame ids (``NodeConfig.frames``).
    enabled : bool
        The ``publish_tf`` parameter; False: nothing is created or sent.
    logger : rclpy.impl.rcutils_logger.RcutilsLogger
        Where a missing type or frame ids tf2 would refuse are reported, once.

    Attributes
    ----------
    via : str or None
        ``'tf2_ros'`` or ``'tf2_msgs'``: what sends; None when nothing is sent.

    """

    def __init__(self, node, frames: dict, enabled: bool, logger):
        self.frames = dict(frames)
        self.via = None
        self._send = None
        if not enabled:
            return
        problem = frame_problem(self.frames)
        if problem is not None:
            logger.error(f'publish_tf: nothing is broadcast on /tf_static: {problem}')
            return
        try:
            from tf2_ros import StaticTransformBroadcaster
        except ImportError:
            try:
                from tf2_msgs.msg import TFMessage
            except ImportError as e:
                logger.warning(MISSING_TYPE.format(error=e))
                return
            publisher = node.create_publisher(TFMessage, TOPIC, STATIC_TF_QOS)
            self._send = lambda transforms: publisher.publish(TFMessage(transforms=transforms))
            self.via = 'tf2_msgs'
        else:  # it keeps every child frame sent and publishes them all in one TFMessage
            self._send = StaticTransformBroadcaster(node).sendTransform  # STATIC_TF_QOS
            self.via = 'tf2_ros'

    def send(self, base_to_base: UncertainPose, tool_to_marker: UncertainPose, stamp) -> None:
        """
        Publish T0 and T1 in one TFMessage (nothing without a type or with publish_tf off).

        Parameters
        ----------
        base_to_base, tool_to_marker : UncertainPose
            T0 (A's base in B's base) and T1 (B's marker in A's tool); m, (w, x, y, z).
        stamp : builtin_interfaces.msg.Time
            The calibration time.

        """
        if self._send is None:
            return
        f = self.frames
        self._send([pose_to_transform(base_to_base, f['base_b'], f['base_a'], stamp),
                    pose_to_transform(tool_to_marker, f['tool'], f['marker'], stamp)])
