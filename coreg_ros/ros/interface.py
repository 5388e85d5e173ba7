"""
coreg_node's ROS interface as data: its name, service names and the QoS profiles both sides use.

The node (``coreg_ros.ros.node``) and the tools that talk to it (``coreg_ros.ros.tools``,
``coreg_ros.ros.echo``) import these from here, so a tool need not import the node.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

NODE_NAME = 'coreg_node'
#: The message type of the pose topics.
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
#: History depth of the subscriptions: absorbs a pause of the stream thread (the GIL held by
#: the estimator or the journal, the intake's own pace) before DDS drops any. Fast DDS (the
#: Jazzy default) holds at most 5000 samples per reader whatever the depth (its default
#: resource limits; measured: a subscribed node that took nothing kept 5000 of 14000 sent), so
#: with it the pause absorbed is 1 s at 5 kHz; what is dropped is counted (``<topic> lost``).
SUB_DEPTH = 10_000

#: QoS of the result topics: late subscribers get the last result.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: Publisher QoS of ``play``: reliable with a deep history, so a reliable subscriber loses
#: nothing, and it still matches best-effort (sensor-data) subscribers.
PLAY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def stream_qos(reliable: bool) -> QoSProfile:
    """
    Return the pose subscriptions' QoS: sensor-data (best effort) or reliable, deep history.

    Parameters
    ----------
    reliable : bool
        Reliable (the node's ``qos_reliable``) instead of best effort.

    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=SUB_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE)


def matching_qos(infos, depth: int = 100, latched: bool = True) -> QoSProfile:
    """
    Return a subscription QoS that every publisher in ``infos`` serves.

    Reliable only if every publisher is reliable, transient-local (late subscribers get the
    stored messages) only if every publisher is and ``latched`` allows it; otherwise best
    effort, volatile, which any publisher matches.

    Parameters
    ----------
    infos : list of rclpy.topic_endpoint_info.TopicEndpointInfo
        The publishers (``Node.get_publishers_info_by_topic``); none: best effort, volatile.
    depth : int
        History depth.
    latched : bool
        Allow transient-local (``echo``: yes, a late echo gets the result; ``record``: no, it
        records what arrives from now on).

    """
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                   for i in infos)
    latched = latched and bool(infos) and all(
        i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def service_name(service: str, node_name: str = NODE_NAME) -> str:
    """
    Return a node's private name in full: ``calibrate`` -> ``/coreg_node/calibrate``.

    Parameters
    ----------
    service : str
        A relative name (made private to ``node_name``) or an absolute one (kept).
    node_name : str
        The node.

    """
    return service if service.startswith('/') else f'/{node_name.strip("/")}/{service}'
