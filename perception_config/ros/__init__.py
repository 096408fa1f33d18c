"""The ROS 2 layer: the only place that imports rclpy and perception_config_interfaces.

Every entry point here applies the project's loopback defaults
(perception_config.launcher.ros_environment) before rclpy creates a participant; importing this package
changes nothing.
"""
