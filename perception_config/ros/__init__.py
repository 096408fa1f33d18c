"""The ROS 2 layer: the only place that imports rclpy and perception_config_interfaces.

Importing this package applies the project's safe defaults to the process environment
(loopback-only discovery, the shipped Fast DDS profile) before rclpy creates a participant.
"""
from .environment import configure_ros_environment

configure_ros_environment()
