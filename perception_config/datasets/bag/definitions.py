"""Message definitions and type hashes of the types the project's bags carry, from rosbags' typestore.

A rosbag2 MCAP stores per type its complete `ros2msg` definition (the type's fields, then for each
nested type a line of 80 `=`, `MSG: pkg/Name` and its fields) and a RIHS01 type hash per topic.
Both come from the rosbags typestore: its ROS 2 standard types (Kilted, the distribution of the
PyPI ROS wheels) plus our own perception_config_interfaces, parsed from their .msg files.

The definitions carry no comments (rosbag2 copies the .msg files with theirs); no reader needs
them: rosbags, mcap-ros2 and Foxglove decode from the fields, and rosbag2 plays the raw CDR
bytes, which are the same (test/test_bag.py checks all three readers and the hashes against the
ROS type descriptions).
"""
from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import BagFormatError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

INTERFACES_PACKAGE = "perception_config_interfaces"
# What the bag writer records, and our other messages (a recorder of the nodes' outputs).
WRITTEN_TYPES = (
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CameraInfo",
    "std_msgs/msg/String",
    f"{INTERFACES_PACKAGE}/msg/ObjectPoses",
    f"{INTERFACES_PACKAGE}/msg/Hypothesis",
    f"{INTERFACES_PACKAGE}/msg/OperatorTrace",
)
# msg_defs/ of a checkout (the source of truth while developing), else the installed package's share/.
REPO_MSG_DEFS = Path(__file__).resolve().parents[3] / "msg_defs" / "msg"


def interfaces_msg_dir() -> Path:
    """The folder of our .msg files: the checkout's msg_defs/msg, else the first ROS prefix
    (AMENT_PREFIX_PATH, then this interpreter's prefix) that installed perception_config_interfaces."""
    if REPO_MSG_DEFS.is_dir():
        return REPO_MSG_DEFS
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
    for prefix in prefixes:
        d = Path(prefix) / "share" / INTERFACES_PACKAGE / "msg"
        if d.is_dir():
            return d
    raise FileNotFoundError(f"no {INTERFACES_PACKAGE} .msg files: neither {REPO_MSG_DEFS} nor share/"
                            f"{INTERFACES_PACKAGE}/msg under {prefixes}")


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """rosbags' ROS 2 Kilted typestore with our interfaces registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    types: dict = {}
    for path in sorted(interfaces_msg_dir().glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(encoding="utf-8"), f"{INTERFACES_PACKAGE}/msg/{path.stem}"))
    store.register(types)
    return store


@functools.lru_cache(maxsize=None)
def definition(type_name: str) -> str:
    """The ros2msg definition text of `type_name` ('pkg/msg/Name') with its nested types;
    BagFormatError for a type neither ROS 2 nor our interfaces define."""
    try:
        return typestore().generate_msgdef(type_name, ros_version=2)[0]
    except Exception as exc:  # rosbags raises its own TypesysError / KeyError for unknown types
        raise BagFormatError(f"no message definition for {type_name!r}: {exc}") from exc


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The RIHS01 type hash ROS 2 computes for `type_name` (rosbag2 writes it per topic)."""
    try:
        return typestore().hash_rihs01(type_name)
    except Exception as exc:
        raise BagFormatError(f"no type hash for {type_name!r}: {exc}") from exc
