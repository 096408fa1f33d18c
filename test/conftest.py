"""Shared fixtures: the real LM-O sample (skipped when ../shared is absent), a procedural box
model, and the rclpy client node of cross-process ROS tests."""
from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Callable

import pytest

from frames import box_mesh
from ros_helpers import pick_domain_id

# The repo and ../shared are siblings: /work/main and /work/shared.
LMO_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lmo"

# ROS processes of this test session get a domain of their own (set before rclpy loads).
os.environ.setdefault("PERCEPTION_CONFIG_TEST_DOMAIN", str(pick_domain_id()))
os.environ["ROS_DOMAIN_ID"] = os.environ["PERCEPTION_CONFIG_TEST_DOMAIN"]
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# Tests stop their child processes with SIGINT (Ctrl-C). A suite started as a background job
# of a non-interactive shell inherits SIGINT ignored, and so would every child: catch it here,
# so children start with the default disposition (a caught signal is reset on exec).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def lmo_root() -> Path:
    """The real BOP LM-O sample; the test is skipped in a clone without ../shared."""
    if not (LMO_ROOT / "models" / "models_info.json").exists():
        pytest.skip(f"real LM-O sample not available at {LMO_ROOT}")
    return LMO_ROOT


@pytest.fixture(scope="session")
def make_box() -> Callable[..., "object"]:
    """Factory: an ObjectModel of a box (metres) with the given size and obj_id."""
    from perception_config.models import make_model

    def make(size: tuple[float, float, float] = (0.1, 0.06, 0.04), obj_id: int = 1):
        v, f = box_mesh(size)
        return make_model(obj_id, v, f, n_points=2000)

    return make


@pytest.fixture(scope="session")
def ros_node():
    """One rclpy context and node for the test process (the client side of cross-process tests)."""
    import rclpy

    from perception_config.ros_environment import configure_ros_environment

    configure_ros_environment()  # the loopback defaults before rclpy.init
    rclpy.init()
    node = rclpy.create_node(f"pytest_client_{os.getpid()}")
    yield node
    node.destroy_node()
    rclpy.try_shutdown()
