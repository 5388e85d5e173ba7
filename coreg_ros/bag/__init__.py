"""
rosbag2 adapter: PoseStamped topics to and from ``PoseStream`` arrays (rosbags only, no rclpy).

Both storage formats (sqlite3, mcap) are read and written; quaternions are (w, x, y, z) in the
arrays and (x, y, z, w) in the messages.
"""

from coreg_ros.bag.posebag import (
    POSE_STAMPED,
    STORAGES,
    list_topics,
    read_pose_bag,
    write_pose_bag,
)

__all__ = ['POSE_STAMPED', 'STORAGES', 'list_topics', 'read_pose_bag', 'write_pose_bag']
