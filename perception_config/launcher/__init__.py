"""Starting the nodes: node resolution, the process supervisor, the ROS environment and Fast DDS
shared-memory housekeeping (no rclpy here)."""
