"""Message type names from a bag, validated before anything is imported for them.

A bag's schema names are data: a replay node that imports `f"{package}.{kind}"` for any of
them lets a crafted bag import any installed module (`this/msg/Zen` imports `this`).
`check_type_name` accepts a name only if it matches TYPE_NAME_PATTERN and its package is a
ROS interface package: listed in the ament index (share/ament_index/resource_index/
rosidl_interfaces under AMENT_PREFIX_PATH, or under the interpreter's prefix where the PyPI
ROS wheels put it) or one of the types our bags carry (definitions.WRITTEN_TYPES). Everything else is
a BagFormatError naming the type; nothing is imported here.
"""
from __future__ import annotations

import functools
import os
import re
import sys
from pathlib import Path

from .definitions import WRITTEN_TYPES
from .errors import BagFormatError

TYPE_NAME_PATTERN = re.compile(r"^[A-Za-z][A-Za-z0-9_]*/(msg/)?[A-Za-z][A-Za-z0-9_]*$")


@functools.lru_cache(maxsize=None)
def interface_packages() -> frozenset[str]:
    """ROS interface packages: those of the ament index (rosidl_interfaces) and of the types we write."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
    found = {name.split("/")[0] for name in WRITTEN_TYPES}
    for prefix in prefixes:
        index = Path(prefix) / "share" / "ament_index" / "resource_index" / "rosidl_interfaces"
        if index.is_dir():
            found.update(p.name for p in index.iterdir() if TYPE_NAME_PATTERN.match(f"{p.name}/x"))
    return frozenset(found)


def normalize_type_name(type_name: str) -> str:
    """'pkg/msg/Name' for both forms a bag may carry: 'pkg/msg/Name' (rosbag2) and 'pkg/Name' (some
    recorders and ROS 1 tools); anything else is returned unchanged (and fails check_type_name)."""
    parts = type_name.split("/") if isinstance(type_name, str) else []
    if len(parts) == 2 and TYPE_NAME_PATTERN.match(type_name):
        return f"{parts[0]}/msg/{parts[1]}"
    return type_name


def check_type_name(type_name: str) -> tuple[str, str]:
    """(package, message name) of a valid 'pkg/msg/Name' (or 'pkg/Name') of a known interface
    package; BagFormatError otherwise."""
    if not isinstance(type_name, str) or not TYPE_NAME_PATTERN.match(type_name):
        raise BagFormatError(f"message type {str(type_name)[:100]!r} is not a ROS type name "
                             "(package/msg/Name of letters, digits and '_')")
    parts = type_name.split("/")
    package, name = parts[0], parts[-1]
    if package not in interface_packages():
        raise BagFormatError(f"message type {type_name!r}: {package!r} is not a known ROS interface package "
                             f"(known: {', '.join(sorted(interface_packages()))})")
    return package, name
