"""
Conversion between ROS messages and coreg_ros data, the one place where quaternion order flips.

ROS messages carry quaternions as (x, y, z, w); everything inside coreg_ros uses (w, x, y, z)
(docs/design.md §3). Stamps are int64 nanoseconds, ``sec * 10**9 + nanosec``.
"""

from __future__ import annotations

from typing import Optional

from builtin_interfaces.msg import Time
from coreg_ros.core.types import UncertainPose
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
import numpy as np

_NS = 1_000_000_000


def stamp_to_ns(stamp: Time) -> int:
    """Return a ``builtin_interfaces/Time`` as int64 nanoseconds."""
    return stamp.sec * _NS + stamp.nanosec


def ns_to_stamp(ns: int) -> Time:
    """Return int64 nanoseconds as a ``builtin_interfaces/Time``."""
    ns = int(ns)
    return Time(sec=ns // _NS, nanosec=ns % _NS)


def pose_stamped_values(msg: PoseStamped) -> tuple:
    """
    Return the numbers of a PoseStamped without allocating arrays.

    Returns
    -------
    values : tuple
        ``(stamp_ns, x, y, z, qw, qx, qy, qz)``: header stamp in ns, position in m in
        ``header.frame_id``, orientation in (w, x, y, z) order.

    """
    p = msg.pose.position
    q = msg.pose.orientation
    s = msg.header.stamp
    return (s.sec * _NS + s.nanosec, p.x, p.y, p.z, q.w, q.x, q.y, q.z)


def make_pose_stamped(stamp_ns: int, frame_id: str, position, quat_wxyz) -> PoseStamped:
    """
    Build a PoseStamped from a stamp (ns), frame id, position (m) and (w, x, y, z) quaternion.

    The values are written as given (NaN stays NaN), so the tools can replay bad data too.
    """
    msg = PoseStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    p = msg.pose.position
    p.x, p.y, p.z = (float(v) for v in position)
    q = msg.pose.orientation
    q.w, q.x, q.y, q.z = (float(v) for v in quat_wxyz)
    return msg


def uncertain_pose_to_msg(pose: UncertainPose, frame_id: str,
                          stamp: Time) -> PoseWithCovarianceStamped:
    """
    Build a PoseWithCovarianceStamped from an UncertainPose.

    Parameters
    ----------
    pose : UncertainPose
        Pose expressed in ``frame_id``; quaternion (w, x, y, z); covariance already in the ROS
        ``PoseWithCovariance`` layout (6×6 row-major over x, y, z, δθx, δθy, δθz).
    frame_id : str
        ``header.frame_id``: the frame the pose is expressed in.
    stamp : builtin_interfaces.msg.Time
        Header stamp (the time of the calibration).

    Notes
    -----
    Without a covariance the diagonal is set to -1, the ``sensor_msgs`` convention for
    "unknown", so that nobody mistakes zeros for certainty.

    """
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    p = msg.pose.pose.position
    p.x, p.y, p.z = (float(v) for v in pose.position)
    q = msg.pose.pose.orientation
    q.w, q.x, q.y, q.z = (float(v) for v in pose.quat_wxyz)
    cov = -np.eye(6) if pose.covariance is None else np.asarray(pose.covariance, dtype=float)
    msg.pose.covariance = [float(v) for v in cov.reshape(36)]
    return msg


def pose_to_transform(pose: UncertainPose, parent: str, child: str,
                      stamp: Time) -> TransformStamped:
    """
    Build a tf2 TransformStamped: the pose of frame ``child`` in frame ``parent``.

    Parameters
    ----------
    pose : UncertainPose
        Position (m) and (w, x, y, z) quaternion of ``child`` in ``parent`` (its covariance
        has no place in TF and is left out).
    parent, child : str
        ``header.frame_id`` and ``child_frame_id`` (tf2's direction: a point p in ``child``
        is ``R p + t`` in ``parent``).
    stamp : builtin_interfaces.msg.Time
        Header stamp.

    """
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t = msg.transform.translation
    t.x, t.y, t.z = (float(v) for v in pose.position)
    q = msg.transform.rotation
    q.w, q.x, q.y, q.z = (float(v) for v in pose.quat_wxyz)
    return msg


def msg_to_uncertain_pose(msg: PoseWithCovarianceStamped) -> UncertainPose:
    """Inverse of ``uncertain_pose_to_msg`` (covariance kept as published)."""
    p = msg.pose.pose.position
    q = msg.pose.pose.orientation
    cov: Optional[np.ndarray] = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)
    return UncertainPose(np.array([p.x, p.y, p.z]), np.array([q.w, q.x, q.y, q.z]), cov)
