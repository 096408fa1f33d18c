"""perception_config: a ROS 2 perception service for robotic picking that configures itself."""

__version__ = "0.1.0"
