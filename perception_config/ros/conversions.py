"""Conversions between ROS messages and the core types, done once at the edge."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose as PoseMsg

from ..core.geometry import Pose, matrix_from_quaternion, quaternion_from_matrix

if TYPE_CHECKING:
    from ..core.scene import Frame


def pose_to_msg(pose: Pose) -> PoseMsg:
    """Core Pose (metres) -> geometry_msgs/Pose."""
    msg = PoseMsg()
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in pose.t)
    q = quaternion_from_matrix(pose.R)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (float(v) for v in q)
    return msg


def msg_to_pose(msg: PoseMsg) -> Pose:
    """geometry_msgs/Pose -> core Pose. Raises ValueError on NaN/inf or a zero quaternion."""
    t = np.array([msg.position.x, msg.position.y, msg.position.z], dtype=np.float64)
    q = np.array([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w], dtype=np.float64)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ValueError("pose contains NaN or infinite values")
    norm = float(np.linalg.norm(q))
    if norm < 1e-6 or abs(norm - 1.0) > 1e-2:
        raise ValueError(f"pose orientation is not a unit quaternion (norm {norm:.4g})")
    return Pose(matrix_from_quaternion(q), t)


def stamp_to_seconds(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def seconds_to_stamp(seconds: float) -> Time:
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"cannot convert {seconds} s to a ROS time stamp")
    ns = int(round(seconds * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_to_nanoseconds(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def frame_to_msgs(frame: "Frame", stamp_ns: int, frame_id: str = "camera_color_optical_frame"):
    """A Frame as the (colour rgb8, depth 16UC1 mm, CameraInfo) messages a camera driver publishes;
    depth None for an RGB-only frame."""
    from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest

    from ..datasets.bag import camera_info_fields, depth_to_image_fields, rgb_to_image_fields

    def header(msg):
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        msg.header.frame_id = frame_id
        return msg

    color = header(Image(**rgb_to_image_fields(frame.rgb)))
    depth = header(Image(**depth_to_image_fields(frame.depth))) if frame.depth is not None else None
    fields = camera_info_fields(frame.K, frame.width, frame.height)
    fields["roi"] = RegionOfInterest(**fields["roi"])
    info = header(CameraInfo(**fields))
    return color, depth, info
