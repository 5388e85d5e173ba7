"""
ROS 2 edge of coreg_ros: the only modules that import rclpy or message packages.

The node: ``node`` (the ``coreg_node`` executable: ``CoregNode`` owns the ROS handles and
assembles its collaborators; ``main``), the collaborators ``sample_store`` (intake, buffers,
journal, sample bags), ``calibrator`` (calibrate, publish and store the result),
``status_publisher`` (/diagnostics) and ``alerts`` (throttled logs, errors, the callback
guards), ``uncertainty_outputs`` and ``live_checks``; ``parameters`` (declared once, from
``config/coreg.yaml``), ``raw_intake`` and ``buffer`` (bulk decoding, bounded preallocated
sample storage with per-reason rejection counters), ``persistence`` (result YAML and sample
bags).
Shared by the node and the tools: ``interface`` (node name, service names, QoS profiles),
``messages`` (message <-> arrays, the (x, y, z, w) <-> (w, x, y, z) boundary) and
``lifecycle`` (the shutdown race: Ctrl-C, SIGTERM).
The tools: ``session`` (``RosSession``), ``tools`` (play, record, call: stand-ins for the ros2
CLI), ``echo``, ``demo`` (the live demo) and ``domain`` (ROS_DOMAIN_ID reservation).
"""
