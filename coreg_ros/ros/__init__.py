"""
ROS 2 edge of coreg_ros: the only modules that import rclpy or message packages.

The node: ``node`` (the ``coreg_node`` executable: assembly, subscriptions, ``main``) with its
parts ``node_services`` (calibrate, reset, save_samples), ``node_storage`` (stored result,
sample journal) and ``node_status`` (/diagnostics); ``parameters`` (declared once, from
``config/coreg.yaml``), ``raw_intake`` and ``buffer`` (bulk decoding, bounded preallocated
sample storage with per-reason rejection counters), ``uncertainty_outputs`` and
``live_checks``, ``persistence`` (result YAML and sample bags).
Shared by the node and the tools: ``interface`` (node name, service names, QoS profiles),
``messages`` (message <-> arrays, the (x, y, z, w) <-> (w, x, y, z) boundary) and
``lifecycle`` (the shutdown race: Ctrl-C, SIGTERM).
The tools: ``session`` (``RosSession``), ``tools`` (play, record, call: stand-ins for the ros2
CLI), ``echo``, ``demo`` (the live demo) and ``domain`` (ROS_DOMAIN_ID reservation).
"""
