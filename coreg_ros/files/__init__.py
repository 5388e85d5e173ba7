"""
Every file format of coreg_ros, at the edge: the numerical core never opens a file.

- ``bag``: rosbag2 recordings (sqlite3 and mcap) of ``geometry_msgs/PoseStamped``, read and
  written with rosbags (in bulk where the layout allows); repairs (``fixbag``, ``salvage``).
- ``csv_poses``: CSV pose exports and the convention checks of two of them.
- ``results``: the one result schema (``coreg calibrate --json``, the node's stored YAML) and
  priors read from it.
- ``parameters``: ROS parameter YAML files (``config/coreg.yaml``).
- ``atomic``: the one atomic writer (results never exist half-written).
"""
