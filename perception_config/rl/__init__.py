"""The Gymnasium environment (`PerceptionConfig-v0`), its settings, the operators behind it (in-process
blocks or ROS services), the episode sources and the one episode loop."""
