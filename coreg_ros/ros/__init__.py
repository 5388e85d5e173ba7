"""
ROS 2 edge of coreg_ros: the only modules that import rclpy or message packages.

``node`` (the ``coreg_node`` executable), ``parameters`` (declared once, from
``config/coreg.yaml``), ``convert`` (message <-> arrays, the (x, y, z, w) <-> (w, x, y, z)
boundary), ``buffer`` (bounded, preallocated sample storage with per-reason rejection
counters), ``persistence`` (result YAML and sample bags), ``tools`` (play, record, call, echo:
stand-ins for the ros2 CLI), ``demo`` (the live demo) and ``domain`` (ROS_DOMAIN_ID reservation).
"""
