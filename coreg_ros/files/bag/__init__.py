"""
rosbag2 adapter: PoseStamped topics to and from ``PoseStream`` arrays (rosbags only, no rclpy).

Both storage formats (sqlite3, mcap) are read and written; quaternions are (w, x, y, z) in the
arrays and (x, y, z, w) in the messages. Topics whose messages share one layout are decoded
and encoded in bulk with numpy (``cdr_pose``, ``bulk_read``, ``bulk_write``); anything else
goes message by message through rosbags (``per_message``), with identical results.
"""

from coreg_ros.files.bag.cdr_pose import decode_pose_stamped, encode_pose_stamped, PoseArrays
from coreg_ros.files.bag.posebag import (
    BULK_ENV,
    list_topics,
    POSE_STAMPED,
    read_pose_bag,
    STORAGES,
    write_pose_bag,
)

__all__ = ['BULK_ENV', 'POSE_STAMPED', 'STORAGES', 'PoseArrays', 'decode_pose_stamped',
           'encode_pose_stamped', 'list_topics', 'read_pose_bag', 'write_pose_bag']
