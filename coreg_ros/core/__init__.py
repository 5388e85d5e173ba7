"""
Pure numerical core: numpy, scipy and the standard library only.

Nothing here imports rclpy, message packages or rosbags (a test enforces it), so the
estimator is usable offline and in notebooks.
"""
