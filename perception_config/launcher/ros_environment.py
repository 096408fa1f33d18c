"""Loopback-only ROS 2 defaults for every process the project starts.

Applied by every entry point right before `rclpy.init` (the nodes, replay-check, the test
client) and to the environment of every child the launcher starts; a value the user already
exported wins. This module does not import rclpy, so the launcher can use it.
- FASTDDS_DEFAULT_PROFILES_FILE: the shipped profile (large shared-memory segment for images,
  UDP receive and send sockets on 127.0.0.1 only, unicast discovery on 127.0.0.1, no multicast).
- ROS_AUTOMATIC_DISCOVERY_RANGE: SYSTEM_DEFAULT with the shipped profile, so that the profile
  alone decides (with LOCALHOST, rmw_fastrtps 9.3 appends a UDP transport without a whitelist
  that binds send sockets on 0.0.0.0 and on the external address); LOCALHOST when the user
  points FASTDDS_DEFAULT_PROFILES_FILE at a profile of their own (Kilted ignores the older
  ROS_LOCALHOST_ONLY).
- ROS_DOMAIN_ID: 42 by default (docs/reference/ros_network.md); any 0-101 the user exports wins.
- RMW_IMPLEMENTATION=rmw_fastrtps_cpp, the middleware the wheels ship.
- AMENT_PREFIX_PATH: the interpreter's prefix, where the PyPI ROS wheels put share/ (nothing
  else sets it outside a sourced ROS installation).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

DEFAULT_DOMAIN_ID = 42
FASTDDS_PROFILE = Path(__file__).resolve().parents[1] / "ros" / "fastdds_profile.xml"


def ros_environment_defaults() -> dict[str, str]:
    """The defaults this project applies, as environment variables (discovery range for the
    shipped profile; `configure_ros_environment` picks LOCALHOST for a user's own profile)."""
    return {
        "FASTDDS_DEFAULT_PROFILES_FILE": str(FASTDDS_PROFILE),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT",
        "ROS_DOMAIN_ID": str(DEFAULT_DOMAIN_ID),
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "AMENT_PREFIX_PATH": sys.prefix,
    }


def configure_ros_environment(env: dict[str, str] | None = None) -> dict[str, str]:
    """Fill in the defaults that are not set in `env` (default: this process's environment)."""
    target = os.environ if env is None else env
    defaults = ros_environment_defaults()
    if target.get("FASTDDS_DEFAULT_PROFILES_FILE") not in (None, "", defaults["FASTDDS_DEFAULT_PROFILES_FILE"]):
        defaults["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    for key, value in defaults.items():
        if not target.get(key):
            target[key] = value
    domain = target["ROS_DOMAIN_ID"]
    if not domain.isdigit() or not 0 <= int(domain) <= 232:
        raise ValueError(f"ROS_DOMAIN_ID must be an integer in 0..232 (0..101 recommended), got {domain!r}")
    return dict(target)
