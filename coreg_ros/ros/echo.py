"""
``coreg echo``: print the messages of a topic readably, with the type and QoS its publishers use.

The formatters (``format_*``) turn one message of the types coreg_node publishes into lines for
a person; ``echo_topic`` finds the publishers, subscribes compatibly (``matching_qos``: a late
echo still gets a transient-local result) and prints each message.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import suppress
import math
from typing import Optional

from coreg_ros.ros.interface import matching_qos
from coreg_ros.ros.lifecycle import RCLError
from coreg_ros.ros.messages import msg_to_uncertain_pose, stamp_to_ns
from coreg_ros.ros.session import RosSession, ToolError
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numpy as np
from rclpy.qos import DurabilityPolicy
from visualization_msgs.msg import Marker, MarkerArray


def format_pose_msg(msg: PoseWithCovarianceStamped, topic: str = '') -> str:
    """Lines for a person: frame, position, quaternion, std from the covariance diagonal."""
    pose = msg_to_uncertain_pose(msg)
    diag = np.diag(pose.covariance)
    std = ['n/a' if d < 0 else f'{math.sqrt(d):.3g}' for d in diag]
    p, q = pose.position, pose.quat_wxyz
    return '\n'.join([
        f'{topic} (frame {msg.header.frame_id}, stamp {_stamp(msg.header):.3f})',
        f'  position  [m]     x {p[0]: .6f}  y {p[1]: .6f}  z {p[2]: .6f}',
        f'  quaternion (wxyz) w {q[0]: .6f}  x {q[1]: .6f}  y {q[2]: .6f}  z {q[3]: .6f}',
        f'  std position [m]  {std[0]}  {std[1]}  {std[2]}',
        f'  std rotation [rad] {std[3]}  {std[4]}  {std[5]}',
    ])


def format_pose_stamped(msg: PoseStamped, topic: str = '') -> str:
    """Lines for a person: frame, stamp, position and quaternion of a PoseStamped."""
    p, q = msg.pose.position, msg.pose.orientation
    return '\n'.join([
        f'{topic} (frame {msg.header.frame_id}, stamp {_stamp(msg.header):.3f})',
        f'  position  [m]     x {p.x: .6f}  y {p.y: .6f}  z {p.z: .6f}',
        f'  quaternion (wxyz) w {q.w: .6f}  x {q.x: .6f}  y {q.y: .6f}  z {q.z: .6f}',
    ])


#: Names of the DiagnosticStatus levels.
LEVEL_NAMES = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}


def _level(status: DiagnosticStatus) -> str:
    level = status.level
    level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
    return LEVEL_NAMES.get(level, str(level))


def format_diagnostics(msg: DiagnosticArray, topic: str = '/diagnostics') -> str:
    """Lines for a person: one ``[LEVEL] name: message`` per status, then its key: value pairs."""
    lines = [f'{topic} (stamp {_stamp(msg.header):.3f}, {len(msg.status)} status)']
    for status in msg.status:
        lines.append(f'  [{_level(status)}] {status.name}: {status.message}')
        lines.extend(f'      {kv.key}: {kv.value}' for kv in status.values)
    return '\n'.join(lines)


_MARKER_TYPES = {v: k.lower() for k, v in vars(Marker).items()
                 if k.isupper() and isinstance(v, int)
                 and k not in ('ADD', 'MODIFY', 'DELETE', 'DELETEALL')}
_MARKER_ACTIONS = {Marker.ADD: 'add', Marker.DELETE: 'delete', Marker.DELETEALL: 'delete all'}


def format_marker_array(msg: MarkerArray, topic: str = '') -> str:
    """Lines for a person: one line per marker (namespace/id, type, frame, position, scale)."""
    lines = [f'{topic} ({len(msg.markers)} markers)']
    for m in msg.markers:
        p, sc = m.pose.position, m.scale
        lines.append(
            f'  {m.ns}/{m.id} {_MARKER_TYPES.get(m.type, m.type)} '
            f'{_MARKER_ACTIONS.get(m.action, m.action)} (frame {m.header.frame_id}) '
            f'at [{p.x:.4f}, {p.y:.4f}, {p.z:.4f}] scale [{sc.x:.4g}, {sc.y:.4g}, {sc.z:.4g}]')
    return '\n'.join(lines)


def _stamp(header) -> float:
    return stamp_to_ns(header.stamp) * 1e-9


#: What ``echo_topic`` can show: ROS type name -> (message class, formatter).
ECHO_TYPES = {
    'geometry_msgs/msg/PoseWithCovarianceStamped': (PoseWithCovarianceStamped, format_pose_msg),
    'geometry_msgs/msg/PoseStamped': (PoseStamped, format_pose_stamped),
    'diagnostic_msgs/msg/DiagnosticArray': (DiagnosticArray, format_diagnostics),
    'visualization_msgs/msg/MarkerArray': (MarkerArray, format_marker_array),
}


def find_publishers(session: RosSession, topic: str, timeout: Optional[float]) -> list:
    """Return the publishers (TopicEndpointInfo) of ``topic`` once any is found; [] on timeout."""
    infos: list = []

    def found() -> bool:  # a shutdown meanwhile (Ctrl-C) is spin_until's to handle
        infos[:] = session.node.get_publishers_info_by_topic(topic)
        return bool(infos)

    session.spin_until(found, timeout)
    return infos


def echo_topic(session: RosSession, topic: str, *, timeout: Optional[float] = None,
               once: bool = False, out: Callable[[str], None] = print) -> int:
    """
    Print the messages of ``topic`` with the type and QoS its publishers use.

    Waits for a publisher, takes its message type (one of ``ECHO_TYPES``) and a QoS every
    publisher serves (``matching_qos``: a transient-local result is received by a late echo,
    a volatile or best-effort stream is received too), then prints each message readably.

    Parameters
    ----------
    session : RosSession
        The ROS context and node that subscribe.
    topic : str
        Full topic name.
    timeout : float, optional
        Seconds to wait for a publisher and then for each message; None: until shutdown.
    once : bool
        Return after the first message.
    out : callable
        Where the lines go.

    Returns
    -------
    printed : int
        Messages printed (0 if the session was shut down, e.g. by Ctrl-C, before any came).

    Raises
    ------
    ToolError
        If no publisher appears within ``timeout``, the topic's type is not one of
        ``ECHO_TYPES``, or no message comes within ``timeout``.

    """
    infos = find_publishers(session, topic, timeout)
    if not infos:
        if not session.ok() or timeout is None:
            return 0
        raise ToolError(f'no publisher of {topic} within {timeout:g} s; is the node running on '
                        f'this ROS_DOMAIN_ID (and the topic name right)?')
    types = list(dict.fromkeys(i.topic_type for i in infos))
    known = [t for t in types if t in ECHO_TYPES]
    if not known:
        raise ToolError(f'{topic} carries {", ".join(types)}; coreg echo shows '
                        f'{", ".join(t.rsplit("/", 1)[-1] for t in ECHO_TYPES)} only')
    msg_type, formatter = ECHO_TYPES[known[0]]
    qos = matching_qos([i for i in infos if i.topic_type == known[0]])
    got: list = []
    sub = session.node.create_subscription(msg_type, topic, got.append, qos)
    printed = 0
    try:
        with session.stoppable():
            while session.ok():
                if not session.spin_until(lambda: bool(got), timeout):
                    break
                while got:
                    out(formatter(got.pop(0), topic))
                    printed += 1
                    if once:
                        return printed
    finally:
        with suppress(RCLError):  # after a Ctrl-C the node may be gone already
            session.node.destroy_subscription(sub)
    if printed == 0 and session.ok() and timeout is not None:
        latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        hint = ('it keeps its last message for late subscribers but has none yet (results '
                'appear after `coreg call calibrate`)' if latched
                else 'it has not published since echo started')
        raise ToolError(f'nothing received on {topic} ({known[0]}) within {timeout:g} s; {hint}')
    return printed
