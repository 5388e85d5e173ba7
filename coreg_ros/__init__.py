"""coreg_ros: coregistration of two pose measurement devices (Ikits 2000) for ROS 2."""

__version__ = '0.1.0'
